"""The dataset registry: which LeRobot dataset each robot owner trains on.

Entries live as ``[tool.zk0.datasets.<name>]`` tables in ``pyproject.toml`` (or another
TOML file named by the ``registry`` run-config key) and are decoded with draccus into
typed ``DatasetEntry`` objects, read and validated once. A simulation client takes the
Nth client entry for partition id N; a SuperNode can name its entry in its node config.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import draccus

from zk0.assets import ensure_dataset
from zk0.assets.datasets import SPECS
from zk0.errors import Zk0Error

PROJECT_ROOT = Path(__file__).resolve().parents[1]
ROLES = ("client", "server")


class RegistryError(Zk0Error):
    """A bad registry or lookup; the message is one sentence naming the bad value."""


@dataclass
class DatasetEntry:
    """One dataset a party can open: where it is and how its cameras map onto the model."""

    repo_id: str
    name: str = ""
    revision: str | None = None
    root: str | None = None  # a local LeRobotDataset root; None = Hub cache under HF_LEROBOT_HOME
    synthetic: bool = False  # generated offline by zk0.assets under the entry's name
    role: str = "client"
    task: str | None = None  # overrides the dataset's own task text when set
    cameras: dict[str, str] = field(default_factory=dict)  # dataset camera -> model camera

    def rename_map(self) -> dict[str, str]:
        """lerobot's rename map: ``observation.images.<source>`` -> ``observation.images.<target>``."""
        return {f"observation.images.{src}": f"observation.images.{dst}" for src, dst in self.cameras.items()}

    def local_root(self) -> Path | None:
        """The dataset root on this machine, generating synthetic datasets on first use."""
        if self.synthetic:
            return ensure_dataset(self.name)
        return Path(self.root).expanduser() if self.root else None


@dataclass
class Registry:
    """All entries, in file order."""

    entries: list[DatasetEntry]

    @property
    def clients(self) -> list[DatasetEntry]:
        return [e for e in self.entries if e.role == "client"]

    def model_cameras(self) -> list[str]:
        """The global model's camera input keys: every mapping target, sorted."""
        targets = {dst for e in self.entries for dst in e.cameras.values()}
        return sorted(f"observation.images.{t}" for t in targets)

    def get(self, key: str) -> DatasetEntry:
        """An entry by registry name or repo id."""
        for entry in self.entries:
            if key in (entry.name, entry.repo_id):
                return entry
        raise RegistryError(
            f"Dataset {key!r} is not in the registry; expected one of {[e.name for e in self.entries]}."
        )

    def get_client(self, key: str) -> DatasetEntry:
        """A client entry by registry name or repo id (what a SuperNode trains on)."""
        entry = self.get(key)
        if entry.role != "client":
            raise RegistryError(f"Dataset {entry.name!r} has role {entry.role!r}; a SuperNode needs a client dataset.")
        return entry

    def for_partition(self, partition_id: int) -> DatasetEntry:
        """The client entry for simulation partition ``partition_id``."""
        clients = self.clients
        if not 0 <= partition_id < len(clients):
            raise RegistryError(
                f"Partition id {partition_id} has no dataset; the registry lists {len(clients)} client "
                f"datasets, so run at most {len(clients)} SuperNodes."
            )
        return clients[partition_id]


def load_registry(path: str | Path = "") -> Registry:
    """Read ``[tool.zk0.datasets]`` from ``path`` ("" = the project's pyproject.toml)."""
    file = Path(path) if path else PROJECT_ROOT / "pyproject.toml"
    if not file.is_absolute():
        file = PROJECT_ROOT / file
    try:
        tables = tomllib.loads(file.read_text()).get("tool", {}).get("zk0", {}).get("datasets", {})
    except OSError as err:
        raise RegistryError(f"Registry file {str(file)!r} cannot be read ({err.strerror}).") from None
    if not tables:
        raise RegistryError(f"Registry file {str(file)!r} has no [tool.zk0.datasets] tables.")
    return Registry([_decode(name, raw) for name, raw in tables.items()])


def _decode(name: str, raw: dict) -> DatasetEntry:
    try:
        entry = draccus.decode(DatasetEntry, {**raw, "name": name})
    except Exception as err:  # draccus raises several types, each with a useful message
        raise RegistryError(f"Registry entry {name!r} is invalid: {err}".rstrip(".") + ".") from None
    if entry.role not in ROLES:
        raise RegistryError(f"Registry entry {name!r} has role {entry.role!r}; expected one of {list(ROLES)}.")
    if entry.synthetic and name not in SPECS:
        raise RegistryError(f"Registry entry {name!r} is marked synthetic but zk0 generates only {sorted(SPECS)}.")
    if not entry.cameras:
        raise RegistryError(
            f'Registry entry {name!r} maps no cameras; add cameras = {{ <dataset camera> = "camera1" }}.'
        )
    return entry
