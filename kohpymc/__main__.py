"""``python -m kohpymc`` is the ``kohpymc`` command."""

from kohpymc.cli import run

if __name__ == "__main__":  # pragma: no cover
    run()
