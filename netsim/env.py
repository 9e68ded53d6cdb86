"""The shared simulation context: the seed from which every component draws its own random stream.

Each stream is keyed by a name (``"down/loss"``, ``"up/jitter"``), so adding a component never shifts another
component's random numbers and the same seed always gives the same results.

Example::

    env = Environment(seed=3)
    rng = env.rng("down/loss")   # numpy Generator, identical for (seed 3, "down/loss") on every run
"""

from __future__ import annotations

import zlib

import numpy as np


class Environment:
    def __init__(self, seed: int = 0):
        self.seed = int(seed)
        self.now_s = 0.0

    def rng(self, stream: str) -> np.random.Generator:
        return np.random.default_rng([self.seed % (2 ** 63), zlib.crc32(stream.encode())])


if __name__ == "__main__":
    env = Environment(seed=3)
    print(env.rng("down/loss").random(3))
