"""facegeo: light-stage face capture to a relightable, re-viewable reflectance field.

Implements Debevec et al., *Acquiring the Reflectance Field of a Human Face* (SIGGRAPH 2000),
with Donner & Jensen's spectral skin model (EGSR 2006) for ground truth.

Heavy dependencies (open3d, trimesh, embreex, xatlas, OpenEXR) are imported lazily by the
modules that need them, so ``import facegeo`` and ``facegeo --help`` stay fast.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
