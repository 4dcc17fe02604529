"""OffLoopOutputs: the network outputs are called from one thread of their own, newest states only."""

import threading

from bridge.outputs import OffLoopOutputs
from visionpos.benchmarks.factories import body_state
from visionpos.server.sinks import Sink


class Recording(Sink):
    """An output that records what it got and on which thread; `gate` holds its first publish."""

    def __init__(self, gate: threading.Event | None = None):
        self.got, self.threads, self.markers = [], set(), []
        self.gate = gate
        self.entered = threading.Event()
        self.arrived = threading.Condition()
        self.started = self.closed = False

    def start(self):
        self.started = True

    def publish(self, states):
        self.threads.add(threading.current_thread().name)
        self.entered.set()
        if self.gate is not None:
            assert self.gate.wait(10.0)
        with self.arrived:
            self.got.append(states)
            self.arrived.notify_all()

    def publish_markers(self, points):
        self.markers.append(points)

    def wait_for(self, n: int) -> bool:
        with self.arrived:
            return self.arrived.wait_for(lambda: len(self.got) >= n, 10.0)

    def stats(self):
        return {"frames": len(self.got)}

    def close(self):
        self.closed = True


class Broken(Sink):
    def publish(self, states):
        raise RuntimeError("bug")


def test_outputs_run_off_the_callers_thread_and_skip_to_the_newest_tick():
    gate = threading.Event()
    out = Recording(gate)
    sink = OffLoopOutputs([out])
    sink.start()
    try:
        assert out.started
        s1, s2, s3 = ([body_state(f"b{i}", i)] for i in (1, 2, 3))
        sink.publish(s1)
        assert out.entered.wait(10.0)  # the thread is now inside the output, held by the gate
        sink.publish(s2)  # returns although the output is stuck
        sink.publish(s3)
        gate.set()
        assert out.wait_for(2)
        assert out.got == [s1, s3]  # s2 was superseded before the thread came back: never sent after s3
        assert out.threads == {"outputs-dispatch"}
        assert sink.stats()["dispatch"]["superseded"] == 1
        assert sink.stats()["Recording"] == {"frames": 2}
    finally:
        sink.close()
    assert out.closed


def test_a_failing_output_does_not_silence_the_others():
    good = Recording()
    sink = OffLoopOutputs([Broken(), good])
    sink.start()
    try:
        for i in range(3):
            sink.publish([body_state("b", 1)])
            assert good.wait_for(i + 1)
        assert sink.counters["errors"] == 3
        sink.publish_markers("points")
        sink.publish([body_state("b", 1)])
        assert good.wait_for(4)
        assert good.markers == ["points"]  # outputs without publish_markers (Broken) are skipped
    finally:
        sink.close()
