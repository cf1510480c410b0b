"""The Python client of the HTTP API, used by ``symgs submit``, ``status``, ``fetch`` and ``demo``."""

from .http import ApiClientError, SymgsClient, zip_folder

__all__ = ["ApiClientError", "SymgsClient", "zip_folder"]
