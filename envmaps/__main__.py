"""Regenerate the procedural maps committed in envmaps/: python -m mcillum.envmaps"""

import os

from mcillum import files

from . import procedural

HERE = os.path.dirname(os.path.abspath(__file__))

#: Committed file name → generator call that makes it (tests check both agree).
COMMITTED = {
    "sky_gradient.exr": lambda: procedural.gradient(width=128, height=64),
}

if __name__ == "__main__":
    for name, make in COMMITTED.items():
        print(files.write_exr(os.path.join(HERE, name), make()))
