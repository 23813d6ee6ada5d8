"""facegeo: light-stage face capture to a relightable, re-viewable reflectance field.

Implements Debevec et al., *Acquiring the Reflectance Field of a Human Face* (SIGGRAPH 2000),
with Donner & Jensen's spectral skin model (EGSR 2006) for ground truth.

Heavy dependencies (open3d, trimesh, embreex, xatlas, OpenEXR) are imported lazily by the
modules that need them, so ``import facegeo`` and ``facegeo --help`` stay fast.
"""

import os as _os

__version__ = "0.1.0"

# numba's parallel kernels (skin fit, relighting) would try the TBB in these wheels first, which
# is older than numba wants: it warns and falls back at the first parallel call. Prefer OpenMP,
# then numba's own workqueue (read when numba is first imported; a user's setting wins).
_os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", "omp workqueue tbb")

__all__ = ["__version__"]
