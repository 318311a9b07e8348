"""Run ``neuromotor ARGS...`` under an address-space limit and write this process's own peak
resident memory (``VmHWM``, kB) to a file at exit:

    python tests/peak_rss.py LIMIT_BYTES OUT_FILE simulate config.toml -o run.npz

Read in the process itself because a parent's ``os.wait4`` counts the image the child was
forked from: a child of a large pytest worker reports the worker's size.
"""

import atexit
import resource
import sys


def _write_peak(path: str) -> None:
    with open("/proc/self/status") as status:
        hwm = next(line for line in status if line.startswith("VmHWM:"))
    with open(path, "w") as out:
        out.write(hwm.split()[1])


if __name__ == "__main__":
    limit, out = int(sys.argv[1]), sys.argv[2]
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))  # a blow-up fails here, not the machine
    atexit.register(_write_peak, out)
    from neuromotor.cli import main

    sys.exit(main(sys.argv[3:]))
