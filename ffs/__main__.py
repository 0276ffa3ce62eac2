"""``python -m ffs``: the command line (:mod:`ffs.cli`)."""

from ffs.cli import console_main

if __name__ == "__main__":
    console_main()
