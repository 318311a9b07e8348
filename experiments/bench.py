"""Speed benchmark (thin wrapper of ``neuromotor bench``; see neuromotor.studies.bench).

    .venv/bin/python experiments/bench.py --idyn ../shared/mocap/mocapbank_19joint.bvh \
        ../shared/mocap/walk_22joint_zyx.bvh --plot docs/bench_throughput.png --json out/bench.json
"""

import sys

from neuromotor.studies.bench import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
