"""Durable job queue in the database, and the code that runs a registration job."""
