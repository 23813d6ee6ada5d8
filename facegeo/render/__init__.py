"""Novel-view rendering of a captured reflectance field (Debevec et al. 2000, §4.5).

* :mod:`facegeo.render.novel` — primary rays → texels → per-source-camera resynthesis (§4.3)
  → Eq. (4) relighting → view-dependent blending → image; the naive baseline.
* :mod:`facegeo.render.detail` — image-space detail: the source cameras' relit captures
  projected per pixel (``render_view(detail=)``).
* camera specs (``orbit:<camera>:<degrees>``, names, JSON, OpenCV FileStorage) and the per-camera skin-model fit
  store live in private modules re-exported here.
"""

from facegeo.render._cameras import (
    FRONT,
    NOVEL_ORBITS,
    front_camera,
    opencv_camera_file,
    orbit_camera,
    parse_camera_spec,
)
from facegeo.render._fitstore import FitStore, FitWriter, light_set
from facegeo.render.detail import SourceImage, project_source_images
from facegeo.render.novel import (
    RenderResult,
    RenderShadows,
    SourceCamera,
    ViewSamples,
    atlas_scene,
    cross_validated_shrinkage,
    load_sources,
    render_shadows,
    render_view,
    shade_texels,
    trace_view,
)

__all__ = [
    "FRONT",
    "FitStore",
    "NOVEL_ORBITS",
    "FitWriter",
    "RenderResult",
    "RenderShadows",
    "SourceCamera",
    "SourceImage",
    "ViewSamples",
    "atlas_scene",
    "cross_validated_shrinkage",
    "front_camera",
    "light_set",
    "load_sources",
    "opencv_camera_file",
    "orbit_camera",
    "parse_camera_spec",
    "project_source_images",
    "render_shadows",
    "render_view",
    "shade_texels",
    "trace_view",
]
