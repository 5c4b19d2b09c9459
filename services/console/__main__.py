"""``python -m services.console``: the same as ``autotune console``."""

from services.cli import entry

if __name__ == "__main__":
    import sys

    entry(["console", *sys.argv[1:]])
