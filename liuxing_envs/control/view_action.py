"""ViewPlanning's action: which view an action names, and the action that names a view."""

from __future__ import annotations

import math

import numpy as np
from gymnasium import spaces

from liuxing_envs.envs.view_planning_settings import ViewActionSettings
from liuxing_envs.validation import as_action, as_index

#: Coverage counts the samples some view of the env's view space sees: with continuous
#: actions, rings at this many elevations across ``elevation_range_deg``, at both ends of
#: ``radius_range``, around the object's middle (see observable_samples in
#: liuxing_envs.sim.objects); with discrete ones, rings at the candidates' elevations.
OBSERVATION_ELEVATION_RINGS = 5


class ViewActions:
    """A view is (azimuth, elevation, radius) about the estimated centre, in rad and m.

    Continuous actions map [-1, 1]³ linearly onto the settings' ranges; discrete ones index
    :attr:`candidate_views` (every discrete azimuth at every discrete elevation, then the
    top view), which the scripted baselines and the greedy oracle also use in either mode.
    """

    def __init__(self, settings: ViewActionSettings) -> None:
        self.mode = settings.action_mode
        self.azimuth_range = np.deg2rad(settings.azimuth_range_deg)
        self.elevation_range = np.deg2rad(settings.elevation_range_deg)
        self.radius_range = np.asarray(settings.radius_range)
        self.candidate_views = _candidate_views(
            settings.discrete_azimuths_deg,
            settings.discrete_elevations_deg,
            settings.discrete_radius,
        )
        if self.mode == "continuous":
            self.space = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
            # The views whose sight decides which samples coverage counts: the action's own.
            self.observation_views = (
                tuple(float(radius) for radius in self.radius_range),
                tuple(
                    float(elevation)
                    for elevation in np.linspace(
                        *settings.elevation_range_deg, OBSERVATION_ELEVATION_RINGS
                    )
                ),
            )
        else:
            self.space = spaces.Discrete(len(self.candidate_views))
            # The candidates' elevations (and the top view) at every azimuth: any yaw.
            elevations = (*(float(e) for e in settings.discrete_elevations_deg), 90.0)
            self.observation_views = ((float(settings.discrete_radius),), elevations)
        # The history's radius feature spans every radius this env can request, so it stays
        # in [0, 1] when discrete_radius lies outside radius_range (the default is inside).
        radii = [*self.radius_range] + (
            [settings.discrete_radius] if self.mode == "discrete" else []
        )
        self.requestable_radii = (float(min(radii)), float(max(radii)))

    def view(self, action) -> tuple[float, float, float]:
        """The view an action names (refusing a malformed action by name)."""
        if self.mode == "discrete":
            return self.candidate_views[as_index(action, int(self.space.n))]
        action = as_action(action, self.space.shape)
        unit = (np.clip(action, -1.0, 1.0) + 1.0) / 2.0
        ranges = np.array([self.azimuth_range, self.elevation_range, self.radius_range])
        values = ranges[:, 0] + unit * (ranges[:, 1] - ranges[:, 0])
        return float(values[0]), float(values[1]), float(values[2])

    def view_to_action(
        self, azimuth: float, elevation: float, radius: float, *, clip: bool = False
    ) -> np.ndarray:
        """The continuous action that requests view (azimuth and elevation in rad, radius in
        m; ``info["viewpoint"]`` gives degrees). Azimuths wrap by whole turns. A view outside
        the action's ranges, which no action requests, is refused with a ValueError, or with
        ``clip`` taken at the nearest one that can be requested, the angularly nearer end of
        a narrowed azimuth range (the scripted baselines' views under narrowed ranges)."""
        values = np.array([azimuth, elevation, radius], dtype=float)
        if not np.isfinite(values).all():
            raise ValueError(f"view_to_action needs finite numbers, got {values.tolist()}")
        low, high = self.azimuth_range
        turn, tolerance = 2 * np.pi, 1e-9
        values[0] = (values[0] - low) % turn + low
        if values[0] > high + tolerance and values[0] - turn >= low - tolerance:
            values[0] -= turn  # a rounding below the range's start, not almost a turn above
        if clip and values[0] > high:  # only a narrowed range: the nearer of its ends
            values[0] = high if values[0] - high <= low + turn - values[0] else low
        ranges = np.array([self.azimuth_range, self.elevation_range, self.radius_range])
        outside = (values < ranges[:, 0] - tolerance) | (values > ranges[:, 1] + tolerance)
        if outside.any() and not clip:
            degrees = np.rad2deg(ranges[:2]).round(2).tolist()
            raise ValueError(
                f"view (azimuth {np.rad2deg(azimuth):.4g} deg, elevation "
                f"{np.rad2deg(elevation):.4g} deg, radius {radius:.4g} m) lies outside the "
                f"action's ranges (azimuth {degrees[0]} deg, elevation {degrees[1]} deg, radius "
                f"{self.radius_range.tolist()} m), so no action requests it; view_to_action takes "
                "radians (info['viewpoint'] is in degrees), or pass clip=True for the nearest "
                "view that can be requested"
            )
        scaled = 2 * (values - ranges[:, 0]) / np.maximum(ranges[:, 1] - ranges[:, 0], 1e-9) - 1
        return np.clip(scaled, -1.0, 1.0).astype(np.float32)


def _candidate_views(
    azimuths_deg, elevations_deg, radius
) -> tuple[tuple[float, float, float], ...]:
    views = [
        (math.radians(az), math.radians(el), float(radius))
        for el in elevations_deg
        for az in azimuths_deg
    ]
    views.append((0.0, math.pi / 2, float(radius)))
    return tuple(views)
