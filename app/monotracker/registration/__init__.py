"""Correspondence-free monocular 2D-3D registration of CT fiducials to one camera image.

Public API: :func:`register` and :class:`Registration` (see :mod:`.api`, :mod:`.result`).
Methods: ``"robust"`` (:mod:`.robust`, the product's), ``"paper"`` (:mod:`.paper`, after
Chen et al. 2025, section 2.2), ``"naive"`` (:mod:`.naive`, benchmark baseline); the
``prior`` fast path (:mod:`.prior`); the accuracy report (:mod:`.report`).
"""

from .api import register
from .result import Registration

__all__ = ["register", "Registration"]
