"""Lighting: direct many-light shading (paper 000, Alg. 3); later VPLs and the lighting grid hierarchy (paper 004)."""
