"""The dashboard: static pages served by the API, talking to the public ``/v1`` API from the browser."""
