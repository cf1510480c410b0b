"""The compression pipeline: a job's stages, each a function of the state the one before returned, in the order
``compress`` runs them.

``compress``     the driver: ``compress`` runs the stages below, ``decompress`` decodes an archive
``job``          what every stage reads (``Job``: settings, device, inputs) and the progress ``Reporter``
``prepare``      load (the scene checked, on the job's device) and views (camera sets, backdrop, floor)
``codec_fit``    the plain scene's archive at the floor, and the codec (``FloorCodec``) that judges each level
``levels``       detect a mirror, drop its right side, fine-tune (``optimize``), keep it or roll it back
``checkpoint``   the level loop's progress saved after each level, for a rerun to resume after
``gating``       colour agreement of a mirror's two sides
``encode``       a state's archive fitted to the floor (``budget``, ``sensitivity``: quantisation, pruning, SH bands)
``result``       the archive kept and its accounting, its evaluation, the report and pictures (``CompressResult``)
``state``        what a level trains and the archive stores (``LevelState``)
"""

from .compress import compress, decompress
from .result import CompressResult

__all__ = ["CompressResult", "compress", "decompress"]
