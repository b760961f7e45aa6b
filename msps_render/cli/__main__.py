"""`python -m msps_render.cli ...` == `msps ...`."""
from msps_render.cli import app

app(prog_name="msps")
