"""Lighting: environment maps, projection onto the light basis, relighting (Debevec et al. 2000
§3.3, Eq. 3–4) and relighting from compressed fields.

Import the submodules directly (``facegeo.lighting.envmap``, ``facegeo.lighting.relight``,
``facegeo.lighting.compress``); this package imports nothing heavy.
"""
