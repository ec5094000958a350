"""``python -m rrtcolearn.cli``: the same as the ``rrtcolearn`` console script."""

from rrtcolearn.cli import main

main()
