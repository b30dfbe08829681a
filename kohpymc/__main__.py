"""``python -m kohpymc`` is the ``kohpymc`` command."""

from kohpymc.cli import main

if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
