"""``python -m trueaxis ARGS``: the same as the console script ``trueaxis ARGS`` (``trueaxis.cli:run``)."""

from .cli import run

if __name__ == "__main__":
    run()
