"""FastAPI app, HTTP client, the `symgs` command line and the dashboard."""
