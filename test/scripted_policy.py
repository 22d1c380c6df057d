"""A submap allocation policy for tests: new submaps exactly where a test says (shared by the persistence and the
submap tests)."""
import math

from gausem_core.slam.allocation import Decision


class ScriptedPolicy:
    """Starts a new submap at the keyframes with the given timestamps."""

    def __init__(self, timestamps):
        self.timestamps = set(timestamps)

    def should_start_new(self, extent, obs, cam_to_world) -> Decision:
        return Decision(obs.timestamp in self.timestamps, math.nan, math.nan, "scripted")


def script_submaps(slam, timestamps):
    """``slam`` with its allocation policy replaced by a :class:`ScriptedPolicy` at ``timestamps``."""
    slam.back_end.allocation = ScriptedPolicy(timestamps)
    return slam
