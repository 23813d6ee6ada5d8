"""Appearance: the synthetic generator's own skin BRDF (:mod:`.brdf`) and Donner & Jensen's
spectral skin model (:mod:`.spectral`)."""
