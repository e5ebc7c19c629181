"""A client's training state on its own disk at checkpoint rounds, so a resumed run continues exactly.

The server's checkpoint holds the global model and its optimiser; what a client's training
carries from round to round (AdamW's moments and the position in its data order) lives in the
client. In checkpoint rounds the server asks (``keep-state`` in the train config) and the client
writes it under its own run folder (``trainer_state/round_<N>.safetensors``: safetensors, no
pickle, never sent anywhere). When the server resumes from round N's checkpoint, each client's
first round of the new run continues from its round N state: the resumed federation trains as if
it had not been interrupted. The two newest states are kept (a crash may come after a client
kept round N's and before the server's checkpoint of it was complete).
"""

from __future__ import annotations

from pathlib import Path

from flwr.app import ArrayRecord
from safetensors import safe_open
from safetensors.torch import save_file

from zk0.learning.training import LocalTrainer

KEPT = 2


def state_file(folder: Path, server_round: int) -> Path:
    return folder / f"round_{server_round}.safetensors"


def keep(folder: Path, server_round: int, trainer: LocalTrainer) -> None:
    """Write the trainer's state after ``server_round`` (renamed into place once complete)."""
    folder.mkdir(parents=True, exist_ok=True)
    final = state_file(folder, server_round)
    partial = final.with_suffix(".partial")
    tensors = {name: t.contiguous() for name, t in trainer.optimizer_record().to_torch_state_dict().items()}
    try:
        save_file(tensors, partial, metadata={"batches-seen": str(trainer.batches_seen)})
    except BaseException:  # a full disk: no half file left where a resumed run would look
        partial.unlink(missing_ok=True)
        raise
    partial.replace(final)
    rounds = sorted(int(p.stem.removeprefix("round_")) for p in folder.glob("round_*.safetensors"))
    for old in rounds[:-KEPT]:
        state_file(folder, old).unlink()


def kept(folder: Path, server_round: int) -> tuple[int, int, ArrayRecord] | None:
    """The newest state this client kept after ``server_round`` or before it: that round, the
    batches seen and the optimizer state (None: none kept). A resumed run finds the one of the
    round it resumes from; a SuperNode restarted mid-run, the one of the last checkpoint round
    before it stopped."""
    rounds = [int(p.stem.removeprefix("round_")) for p in folder.glob("round_*.safetensors")]
    earlier = [r for r in rounds if r <= server_round]
    if not earlier:
        return None
    with safe_open(state_file(folder, max(earlier)), framework="pt") as state:
        seen = int(state.metadata()["batches-seen"])
        return max(earlier), seen, ArrayRecord({name: state.get_tensor(name) for name in state.keys()})
