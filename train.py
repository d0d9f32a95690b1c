"""Reconstruct a flame: ``python train.py [key=value ...]``, the same command as ``flamerecon``
(:mod:`flamerecon.run.train`; Hydra, see conf/train.yaml); ``python train.py view RUN_DIR`` is
``flamerecon view`` (:mod:`flamerecon.viewer.command`).

Bad input ends in one line naming the file and field (exit status 2; ``debug=true`` for the
traceback); ``resume=RUN_DIR`` continues an interrupted run in its folder; SIGINT, SIGTERM and
SIGHUP end it with one line and exit status 130, from the first line on.
"""

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

from flamerecon.__main__ import main

if __name__ == "__main__":
    main()
