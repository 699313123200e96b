"""``python -m stereoseed``: the stereoseed command."""
from stereoseed.cli import run

run()
