"""``python -m stereoseed.cli``: the stereoseed command."""
from stereoseed.cli import run

run()
