"""The HTTP API: the FastAPI app, its routes, dependencies and error answers. It never imports torch."""
