"""``python -m sarship``: the command line (same as the ``sarship`` console script)."""

from sarship.launch import console

if __name__ == "__main__":
    console()
