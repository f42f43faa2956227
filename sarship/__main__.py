"""``python -m sarship``: the command line (same as the ``sarship`` console script)."""

from sarship.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
