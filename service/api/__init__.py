"""HTTP API: routes, dependencies, error documents and middleware."""
