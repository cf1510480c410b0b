"""The error every dataset loader raises, with a machine-readable code."""

from __future__ import annotations


class DatasetError(ValueError):
    """A dataset that cannot be loaded; ``code`` says why in a machine-readable word.

    Codes: not_found, unknown_layout, bad_split, bad_json, bad_transforms, image_missing, bad_image, image_too_large,
    malformed, unknown_camera_model, unsupported_camera_model (a fisheye or panoramic model, which no pinhole holds
    whole), distorted_camera (a lens too strong to undo), camera_missing, empty; and, from the pipeline, images_mismatch
    (``views.check_photographs``) and too_few_images (``views.dataset_views``).
    """

    def __init__(self, code: str, message: str) -> None:
        super().__init__(code, message)  # both, so a pickled copy (Celery's failure hook) keeps the code
        self.code, self.message = code, message

    def __str__(self) -> str:
        return self.message
