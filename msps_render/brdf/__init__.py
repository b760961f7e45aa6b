"""Measured BRDFs: MERL table IO and lookup (`merl`), analytic table generation
(`analytic`), the Mitsuba `merl` BSDF plugin (`plugin`, imports Mitsuba lazily)
and the material library (`library`). See docs/brdf.md."""
