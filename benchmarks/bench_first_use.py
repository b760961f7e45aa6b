"""What a new worker process pays the first time it uses each shipped measured table (CPU s).

Usage:  MSPS_THREADS=1 PYTHONPATH=. .venv/bin/python benchmarks/bench_first_use.py

Maps every built-in Neural-BRDF table (baking it into the cache if absent) and reads or fits its
sampling lobe, as a render worker does before the first frame that uses it.  Run it twice: the
first run may bake tables and write their `.lobe.json` files; the second is what every later worker
pays.  Results: docs/benchmarks.md "A worker's first use of the measured tables".
"""
from __future__ import annotations

import time

from msps_render.brdf import nbrdf
from msps_render.render import merl_bsdf


def main() -> None:
    names = nbrdf.builtin_names()
    t0 = time.process_time()
    for n in names:
        merl_bsdf._load_table(str(nbrdf.baked_table(nbrdf.weights_path(n))))
    print(f"{len(names)} tables, CPU s {time.process_time() - t0:.3f}")


if __name__ == "__main__":
    main()
