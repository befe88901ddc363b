"""Cross-cutting service plumbing: settings and logging."""
