"""The compression pipeline, in the order a job runs it.

``compress``  views, mirror levels, reductions and the archive, with progress and checkpoints (``compress.py``)
``levels``    detect a mirror, drop its right side, fine-tune (``optimize``), keep it or roll it back
``gating``    colour agreement of a mirror's two sides
``prune``     Gaussians and SH bands the renders do not miss
``budget``    the PSNR budget shared by the lossy stages; quantisation steps fitted to it
``encode``    the stages after the mirrors, their accounting, and the archive
``state``     what a level trains and the archive stores (``LevelState``)
"""

from .compress import CompressResult, compress, decompress

__all__ = ["CompressResult", "compress", "decompress"]
