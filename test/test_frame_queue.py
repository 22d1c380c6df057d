"""NewestFrameQueue (gausem_ros.nodes.common): the newest frame wins, and each frame handed over hears of exactly the
frames skipped before it, also those dropped while an older one was being processed."""
from gausem_ros.nodes.common import NewestFrameQueue


class ManualGuard:
    """A node stand-in whose guard condition runs only when the test says (as an executor would, later)."""

    def __init__(self):
        self.callback, self.triggered = None, 0

    def create_guard_condition(self, callback, callback_group=None):
        del callback_group
        self.callback = callback
        return self

    def trigger(self):
        self.triggered += 1


def test_each_frame_hears_of_the_frames_skipped_before_it_and_no_later_ones():
    node, handed, superseded = ManualGuard(), [], []
    queue = None

    def process(item, arrived, skipped):
        del arrived
        handed.append((item, skipped))
        if item == "b":  # while b is processed: c is dropped upstream, d is put and superseded by e
            queue.skip()
            queue.put("d")
            queue.put("e")

    queue = NewestFrameQueue(node, process, superseded.append)
    queue.skip(2)  # two frames dropped before the first one arrived
    queue.put("a")
    queue.put("b")  # a is superseded
    assert superseded == ["a"] and queue.pending == 1 and node.triggered == 2  # each put on an idle queue
    node.callback()
    assert handed == [("b", 3)] and superseded == ["a", "d"]
    assert node.triggered == 3  # not by the puts while busy; e was left pending: once when b was done
    node.callback()
    assert handed == [("b", 3), ("e", 2)] and queue.pending == 0
    queue.skip()
    queue.clear()  # a reset forgets what was skipped
    queue.put("f")
    node.callback()
    assert handed[-1] == ("f", 0)


def test_a_frame_waits_while_not_ready():
    node, handed = ManualGuard(), []
    ready = [False]
    queue = NewestFrameQueue(node, lambda item, arrived, skipped: handed.append(item), lambda _: None,
                             ready=lambda: ready[0])
    queue.put("a")
    node.callback()
    assert handed == [] and queue.pending == 1
    ready[0] = True
    queue.wake()
    node.callback()
    assert handed == ["a"]


def test_a_drop_newer_than_the_pending_frame_counts_towards_the_frame_after_it():
    node, handed = ManualGuard(), []
    queue = NewestFrameQueue(node, lambda item, arrived, skipped: handed.append((item, skipped)), lambda _: None)
    queue.put("a", stamp=1.0)
    queue.skip(stamp=0.5)  # older than a: before it
    queue.skip(stamp=2.0)  # dropped after a arrived: after it
    queue.skip()  # no stamp: before the pending frame
    node.callback()
    queue.put("c", stamp=3.0)
    queue.skip(stamp=4.0)
    queue.put("e", stamp=5.0)  # c superseded, and the drop after it is now before e
    node.callback()
    assert handed == [("a", 2), ("e", 3)]  # e: the drop after a, c and the drop after c


def test_an_item_is_in_progress_from_its_taking_until_settled_or_done():
    node, seen = ManualGuard(), []
    queue = None

    def process(item, arrived, skipped):
        del arrived, skipped
        seen.append((item, queue.pending, queue.in_progress))
        if item == "a":
            queue.settle()  # counted (processed or dropped) before the processing ends
            seen.append(("settled", queue.in_progress))

    queue = NewestFrameQueue(node, process, lambda _: None)
    queue.put("a")
    assert (queue.pending, queue.in_progress) == (1, 0)
    node.callback()
    queue.put("b")
    node.callback()  # b is not settled by process: done all the same
    assert seen == [("a", 0, 1), ("settled", 0), ("b", 0, 1)] and queue.in_progress == 0
