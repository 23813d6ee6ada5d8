"""Surface: Embree-backed ray casting and visibility (:mod:`.visibility`); the atlas and the
surface reflectance field projection will live here too."""
