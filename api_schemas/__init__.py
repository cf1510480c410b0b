"""Pydantic models: the contract between client, API and worker."""
