"""Studies beyond the paper (docs/beyond.rst): the command line of :mod:`validation.beyond`.

::

    PYTHONPATH=. python scripts/beyond_paper.py run STUDY [--reduced] [--out DIR] [--num-cpus N] [--address ADDR] ...
    PYTHONPATH=. python scripts/beyond_paper.py ship STUDY [--runs DIR [DIR ...]] [--dest DIR]
    PYTHONPATH=. python scripts/beyond_paper.py nmpc [--dest DIR] [--seeds S ...] [--progress]
"""

from validation.beyond import main

if __name__ == "__main__":
    raise SystemExit(main())
