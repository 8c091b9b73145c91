"""The `workspace:` config section: where the robot may go beyond its pose limits
(cdpr.workspace_check), and the map `cdprd workspace` computes (tuning.workspace_map).

    workspace:
      margin: 5.0          # N: the capacity margin every sampled reference keeps at rest
      interference: true   # refuse cables closer than their diameters or through the body
      map: null            # the map's file; null: STATE_DIR/ROBOT.workspace
      step: 0.02           # m, the map's grid
      tilt: null           # rad, the map's orientations beside home; null: safety.tilt_max
      payload_max: 0.0     # kg: the map holds for payloads from 0 to this at the CoM

Validation refuses a trajectory, path or goto whose sampled references need, at rest, a
wrench less than `margin` inside the wrenches the cables can give (with the platform's
current mass and centre of mass: the payload estimate), or whose cables interfere.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, NonNegativeFloat

from cdpr.description import StrictModel
from cdpr.workspace_map import MapSettings


class WorkspaceConfig(StrictModel):
    """The `workspace:` section (every key optional).

    margin: the capacity margin (N) every sampled reference must keep: the radius of the
      largest ball of wrenches (moments divided by the attachments' RMS radius) around
      the wrench that holds the platform at rest that the cables' tensions in
      [t_min, force_max] still give: a push that large is still balanced.
    interference: refuse references where two cables come closer than their diameters
      (actuator.cable_diameter) or a cable runs through the platform's body.  On unless
      set false: the reference robot's configs do, because its crossed cable pairs are
      idealised and pass through each other at every untilted pose (`cdprd workspace
      --interference` shows where).
    map: the file `cdprd workspace` writes and `check-config` reads (relative to the
      config); null: STATE_DIR/ROBOT.workspace, else none.
    step: the map's grid spacing (m).
    tilt: the map's orientations: home and eight tilted by this much (rad) about the
      horizontal axes; null: safety.tilt_max.
    payload_max: the map's payload range (kg), from 0, at the platform's centre of mass.
    """

    margin: NonNegativeFloat = 5.0
    interference: bool = True
    map: str | None = None
    step: Annotated[float, Field(ge=0.005, le=0.5)] = 0.02
    tilt: Annotated[float, Field(ge=0.0, le=1.5)] | None = None
    payload_max: NonNegativeFloat = 0.0

    def map_settings(
        self,
        tilt_max: float,
        step: float | None = None,
        tilt: float | None = None,
        payload_max: float | None = None,
        margin: float | None = None,
        interference: bool | None = None,
    ) -> MapSettings:
        """The map settings of this section, the tilt defaulting to `tilt_max`
        (safety.tilt_max); each value given (not None) replaces the section's."""
        tilt = (tilt_max if self.tilt is None else self.tilt) if tilt is None else tilt
        return MapSettings(
            step=self.step if step is None else step,
            tilt=tilt,
            payload=(0.0, self.payload_max if payload_max is None else payload_max),
            margin=self.margin if margin is None else margin,
            interference=self.interference if interference is None else interference,
        )
