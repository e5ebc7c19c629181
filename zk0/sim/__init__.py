"""The SO-101 pick-up task in MuJoCo: scene, gymnasium env (a lerobot ``EnvConfig``), scripted
expert and demonstrations. It knows nothing of SmolVLA or the federation: zk0.learning.closed_loop rolls
a policy out in it.

MuJoCo renders headless through EGL unless ``MUJOCO_GL`` says otherwise; it reads the variable
when its first renderer is made, so it is set here, before any of these modules loads MuJoCo.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from zk0.common.errors import Zk0Error  # noqa: E402


class RenderError(Zk0Error):
    """This machine cannot render the cameras; one sentence naming ``MUJOCO_GL``."""


def cannot_render(err: BaseException) -> RenderError:
    """The one sentence for a MuJoCo that cannot load or open its ``MUJOCO_GL`` backend."""
    backend = os.environ.get("MUJOCO_GL", "")
    reason = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
    return RenderError(
        f"MuJoCo cannot render here with MUJOCO_GL={backend!r} ({reason}); expected MUJOCO_GL=egl with EGL "
        "installed (Debian: libegl1) or MUJOCO_GL=osmesa with libosmesa6 (./train.sh installs them as root)."
    )


def load_mujoco():
    """``import mujoco``, which loads the ``MUJOCO_GL`` backend, or the one sentence if it cannot."""
    try:
        import mujoco
    except (ImportError, RuntimeError, AttributeError) as err:
        raise cannot_render(err) from None
    return mujoco
