"""Measured BRDFs and the material library (numpy only): MERL table IO and lookup (`merl`),
analytic table generation (`analytic`), built-in Neural-BRDF fits (`nbrdf`), the analytic
material families (`families`, registry `FAMILIES`) and the catalogue (`library`).
The Mitsuba `merl` BSDF plugin is `msps_render.render.merl_bsdf`. See docs/brdf.md."""
