"""The saved workspace map (`cdprd workspace`, tuning.workspace_map computes it): a
grid's capacity margins (N) at a set of orientations, or the first reason each point is
out, with a fingerprint of everything it was computed from, so that a map is used only
while the robot file, the workspace box, the environment and the settings are those it
was made from.  Read by check-config and the live view; here, apart from its computation,
because the companion process reads it and never loads the offline tools.

The file: 4 bytes of header length, a JSON header (format, fingerprint, origin, step,
shape, orientations, settings, seconds), then the margins as zlib-compressed
little-endian int16 in 0.1 N, the reason codes stored below -32760 where no margin was
computed.
"""

from __future__ import annotations

import hashlib
import json
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdpr.body import Environment
from cdpr.robot import Robot

Array = NDArray[np.float64]

FORMAT = 1  # of the saved map: a file of another format is stale
REASONS = ("in the workspace", "outside the box", "environment", "cable length", "interference")
IN, BOX, ENVIRONMENT, LENGTH, INTERFERENCE = range(len(REASONS))
_DECINEWTONS = 10.0  # margins are saved as int16 in 0.1 N
_NOT_COMPUTED = np.iinfo(np.int16).min  # saved margin where a geometric reason ruled


@dataclass(frozen=True)
class MapSettings:
    """What a map is computed for: grid `step` (m), `tilt` (rad) of the orientations
    beside home, the payload range (kg, at the platform's centre of mass), the
    capacity `margin` (N) a point needs to count, and whether cables may not interfere."""

    step: float = 0.02
    tilt: float = 0.6
    payload: tuple[float, float] = (0.0, 0.0)
    margin: float = 0.0
    interference: bool = True


@dataclass
class WorkspaceMap:
    """Margins (N) on the grid `origin + step * index` (shape nx, ny, nz) at each of
    `quaternions`; `reason[o, i, j, k]` is IN where `margin` was computed (NaN elsewhere)."""

    origin: Array
    step: float
    quaternions: Array
    margin: NDArray[np.float32]
    reason: NDArray[np.int8]
    settings: MapSettings
    fingerprint: str
    seconds: float = 0.0
    points: int = field(init=False)

    def __post_init__(self) -> None:
        self.points = int(self.reason.size)

    def inside(self) -> NDArray[np.bool_]:
        """Points in the workspace: geometrically admissible with the required margin."""
        return (self.reason == IN) & (self.margin >= self.settings.margin)

    def positions(self) -> Array:
        """The grid's positions (nx x ny x nz x 3, m)."""
        axes = [self.origin[a] + self.step * np.arange(n) for a, n in enumerate(self.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.margin.shape[1:])  # type: ignore[return-value]

    def summary(self) -> dict[str, Any]:
        """Volume (m^3) and fraction of the box per orientation and where every
        orientation is possible, the worst and the best margin inside, the reasons'
        counts, and the computation's speed."""
        inside = self.inside()
        cell = self.step**3
        margins = self.margin[inside]
        counts = {name: int((self.reason == code).sum()) for code, name in enumerate(REASONS)}
        counts["wrench"] = int(((self.reason == IN) & ~inside).sum())
        return {
            "volume_m3": float(inside.all(axis=0).sum() * cell),
            "volume_per_orientation_m3": [float(v * cell) for v in inside.sum(axis=(1, 2, 3))],
            "fraction": float(inside.all(axis=0).mean()),
            "worst_margin_n": float(margins.min()) if margins.size else None,
            "best_margin_n": float(margins.max()) if margins.size else None,
            "points": self.points,
            "orientations": len(self.quaternions),
            "reasons": counts,
            "seconds": round(self.seconds, 3),
            "points_per_second": round(self.points / self.seconds) if self.seconds else None,
        }

    def save(self, path: str | Path) -> None:
        """The map as one file: a JSON header and the zlib-compressed int16 margins."""
        saved = np.where(
            self.reason == IN,
            # -inf: no margin at all (a rank-deficient Jacobian); saved as the lowest
            np.round(np.clip(np.nan_to_num(self.margin), -3200.0, 3200.0) * _DECINEWTONS),
            _NOT_COMPUTED + self.reason.astype(np.int16),
        ).astype("<i2")
        header = {
            "format": FORMAT,
            "fingerprint": self.fingerprint,
            "origin": self.origin.tolist(),
            "step": self.step,
            "shape": list(self.margin.shape),
            "quaternions": self.quaternions.tolist(),
            "settings": _settings_json(self.settings),
            "seconds": self.seconds,
        }
        body = zlib.compress(saved.tobytes(), 6)
        raw = json.dumps(header).encode()
        Path(path).write_bytes(len(raw).to_bytes(4, "little") + raw + body)

    @classmethod
    def load(cls, path: str | Path) -> WorkspaceMap:
        """A saved map; ValueError naming the problem if the file is not one."""
        data = Path(path).read_bytes()
        try:
            size = int.from_bytes(data[:4], "little")
            header = json.loads(data[4 : 4 + size])
            if header.get("format") != FORMAT:
                raise ValueError(f"format {header.get('format')!r}, not {FORMAT}")
            shape = tuple(int(n) for n in header["shape"])
            saved = np.frombuffer(zlib.decompress(data[4 + size :]), "<i2").reshape(shape)
            settings = MapSettings(**{k: _tuple(v) for k, v in header["settings"].items()})
        except (ValueError, KeyError, TypeError, zlib.error) as exc:
            raise ValueError(f"{path}: not a workspace map: {exc}") from None
        computed = saved > _NOT_COMPUTED + len(REASONS)
        reason = np.where(computed, IN, saved - _NOT_COMPUTED).astype(np.int8)
        margin = np.where(computed, saved / _DECINEWTONS, np.nan).astype(np.float32)
        return cls(
            np.array(header["origin"]),
            float(header["step"]),
            np.array(header["quaternions"]),
            margin,
            reason,
            settings,
            str(header["fingerprint"]),
            float(header["seconds"]),
        )


def _settings_json(settings: MapSettings) -> dict[str, Any]:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in vars(settings).items()}


def _tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


def fingerprint(
    robot: Robot,
    lower: Sequence[float],
    upper: Sequence[float],
    environment: Environment,
    settings: MapSettings,
) -> str:
    """A hash of everything a map depends on: the robot file's contents, the workspace
    box, the environment and the settings."""
    text = json.dumps(
        {
            "format": FORMAT,
            "robot": robot.spec.model_dump(mode="json"),
            "box": [list(map(float, lower)), list(map(float, upper))],
            "planes": [list(map(_tuple, p)) for p in environment.planes],
            "boxes": [list(map(_tuple, b)) for b in environment.boxes],
            "settings": _settings_json(settings),
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def shell(workspace: WorkspaceMap, orientation: int, limit: int = 20_000) -> tuple[Array, Array]:
    """The workspace's boundary at one orientation, for a 3-D view: the positions (N x 3)
    and margins (N) of its points with a neighbour outside, every k-th along each axis
    so that at most `limit` are left."""
    inside = workspace.inside()[orientation]
    padded = np.pad(inside, 1)
    interior = inside.copy()
    for axis in range(3):
        for shift in (-1, 1):
            interior &= np.roll(padded, shift, axis=axis)[1:-1, 1:-1, 1:-1]
    boundary = inside & ~interior
    stride = 1
    while boundary[::stride, ::stride, ::stride].sum() > limit:
        stride += 1
    kept = np.zeros_like(boundary)
    kept[::stride, ::stride, ::stride] = boundary[::stride, ::stride, ::stride]
    index = np.argwhere(kept)
    positions = workspace.origin + workspace.step * index
    return positions, workspace.margin[orientation][kept].astype(float)
