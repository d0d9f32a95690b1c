"""The ``flamerecon`` command (also ``python -m flamerecon``): ``flamerecon [key=value ...]``
reconstructs (= ``python train.py``, :mod:`flamerecon.run.train`); ``flamerecon view RUN_DIR``
opens the web viewer (:mod:`flamerecon.viewer.command`)."""

from __future__ import annotations

import sys


def main() -> None:
    from flamerecon.interrupt import install

    install()  # first: a stop signal from here on ends in one line, exit status 130
    if len(sys.argv) > 1 and sys.argv[1] == "view":
        from flamerecon.viewer.command import main as view

        raise SystemExit(view(sys.argv[2:]))
    from flamerecon.run.train import main as train

    train()


if __name__ == "__main__":
    main()
