"""The API's reference page, ``/docs`` (Swagger UI), from files the service ships."""
