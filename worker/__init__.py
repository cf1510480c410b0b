"""Celery app, tasks, job store and artifact storage."""
