"""Registers zk0's simulated SO-101 (``--env.type=zk0_so101``) when lerobot loads its env plugins."""

import zk0.sim.lerobot_env  # noqa: F401  (its EnvConfig registers itself on import)
