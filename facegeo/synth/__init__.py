"""Synthetic light-stage capture: procedural or real heads, solid-texture skin, a reference
renderer, and a writer that produces scans in exactly the format a real rig writes."""
