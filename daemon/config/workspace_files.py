"""The workspace map a daemon config names (cdpr.workspace_map): the saved map if it is
still this config's: the same robot, box and environment, and the `workspace:` section's
margin, interference and payload range.  Its grid step and tilt may differ (`cdprd
workspace --step 0.05` is a coarser map of the same workspace, not another one)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from cdpr.workspace_map import WorkspaceMap, fingerprint

if TYPE_CHECKING:
    from daemon.config import DaemonConfig


def stored_map(config: DaemonConfig) -> tuple[WorkspaceMap | None, str]:
    """The config's saved map if it is there and was computed from this robot, box,
    environment, margin, interference and payload range (at any step and tilt); else
    None and why not."""
    path = config.workspace_map_path()
    if path is None:
        return None, "no map file: set workspace.map or state_dir"
    if not path.exists():
        return None, f"no map at {path}"
    try:
        saved = WorkspaceMap.load(path)
    except (OSError, ValueError) as exc:
        return None, str(exc)
    lower, upper = config.workspace_box
    expected = fingerprint(config.robot, lower, upper, config.environment, saved.settings)
    wanted = config.workspace.map_settings(
        config.safety.tilt_max, step=saved.settings.step, tilt=saved.settings.tilt
    )
    if saved.fingerprint != expected or saved.settings != wanted:
        return None, (
            f"the map at {path} is stale: the robot file, the config or the workspace "
            "settings changed since it was computed"
        )
    return saved, f"map {path}"
