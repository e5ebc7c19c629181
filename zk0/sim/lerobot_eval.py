"""``python -m zk0.sim.lerobot_eval``: lerobot's own ``lerobot-eval``, with zk0's env registered.

lerobot imports third-party envs only from distributions named ``lerobot_env_*``; zk0 is not
one, so this module registers ``--env.type=zk0_so101`` and hands every argument to lerobot's
command unchanged, e.g.::

    python -m zk0.sim.lerobot_eval --policy.path=outputs/<run>/models/best --env.type=zk0_so101 \\
        --eval.n_episodes=20 --eval.batch_size=1 --output_dir=outputs/<run>/lerobot-eval
"""

from lerobot.scripts.lerobot_eval import main

import zk0.sim.lerobot_env  # noqa: F401  (registers the zk0_so101 env config)

if __name__ == "__main__":
    main()
