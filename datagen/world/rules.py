"""The ego's record against stop signs and red lights, kept step by step whoever drives it.

The expert's rules read it (expert.ExpertInput.stop_done: the full stop at a stop-controlled
entry is done), World.truth() reports it to a scorer (EgoTruth.entered_on_red) and
World.stats counts red-light entries. World frame, metres, seconds.
"""

from __future__ import annotations

from collections.abc import Callable

import datagen.world.expert as expert
import datagen.world.perception as perception
import datagen.world.route as route
from datagen.world.sumo import Network, Snapshot


def stop_foes(net: Network, links: tuple[route.Link, ...]) -> frozenset[str] | None:
    """Internal lanes of passages that conflict with the ego's through its next stop sign
    (sumo.Network.internal_foes), from the ego's next links; None without one."""
    via = next((k.via_lane_id for k in links if k.state in ("s", "w")), "")
    return net.internal_foes(via) if via else None


class RuleBook:
    """Full stops at stop-controlled entries and entries into a junction on red.

    Attributes:
        stop_done_lane: the lane whose stop-controlled entry the ego has completed its full
            stop at (None: none; entering a junction forgets it).
        entered_on_red: in the last step the ego entered a junction through a red link.
        red_light_violations: such entries in the episode.
    """

    def __init__(self, net: Network, step_s: float, is_kerb: Callable[[str], bool]):
        """`step_s`: the SUMO step, s; `is_kerb`: perception.is_kerb of a lane id."""
        self._net = net
        self._step_s = step_s
        self._is_kerb = is_kerb
        self.stop_done_lane: str | None = None
        self.entered_on_red = False
        self.red_light_violations = 0
        self._stop_wait_s = 0.0

    def note_stop(self, lane0: str, snap: Snapshot, signals: route.Signals) -> None:
        """Full stop at a stop-controlled entry: held STOP_WAIT_S (and the junction clear), the
        entry is done; entering a junction forgets it. `lane0`: the ego's lane before the step,
        `snap`: after it, `signals`: those read before it."""
        lane1, v1 = snap.ego.lane_id, snap.ego.speed_mps
        if lane1 != lane0 and lane1.startswith(":"):
            self.stop_done_lane = None
        stop_d = signals.stop_distance_m
        if (
            stop_d is not None
            and stop_d < expert.STOP_SIGN_MARGIN_M + 3.0
            and v1 < expert.STOPPED_MPS
        ):
            self._stop_wait_s += self._step_s
            if self._stop_wait_s >= expert.STOP_WAIT_S and perception.junction_clear(
                snap.agents,
                signals.stop_junction,
                self._is_kerb,
                stop_foes(self._net, snap.links),
            ):
                self.stop_done_lane = lane1
        else:
            self._stop_wait_s = 0.0

    def note_red_light(self, lane0: str, lane1: str, first_state: str) -> None:
        """Did the ego enter a junction (an internal lane) through a link that was red? `lane0`,
        `lane1`: its lane before and after the step; `first_state`: SUMO's state of its next
        link before the step."""
        self.entered_on_red = (
            lane1.startswith(":") and not lane0.startswith(":") and first_state in ("r", "u")
        )
        if self.entered_on_red:
            self.red_light_violations += 1
