"""``node-sim``: start a scene's node twins on a bus (implemented with the node rig, issue 4)."""

import sys


def main(argv=None) -> int:
    print("node-sim: not built yet", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
