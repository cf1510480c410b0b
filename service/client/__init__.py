"""The Python client of the HTTP API, used by ``symgs submit``, ``status``, ``fetch`` and ``demo``."""

from .http import ApiClientError, SymgsClient, UnsafeArtifactName, zip_folder

__all__ = ["ApiClientError", "SymgsClient", "UnsafeArtifactName", "zip_folder"]
