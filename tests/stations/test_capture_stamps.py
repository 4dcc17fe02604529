"""Capture stamps are mid-exposure: the Pi camera source adds half the frame's exposure to the sensor's
start-of-exposure timestamp (a fake picamera2 module stands in for the camera)."""

import sys
import time
import types

import numpy as np

from stations.config import SourceConfig
from stations.sources import Picamera2Source, mid_exposure_offset_ns


class _Request:
    def __init__(self, metadata):
        self.metadata = metadata

    def make_array(self, name):
        return np.zeros((96, 64), np.uint8)

    def get_metadata(self):
        return self.metadata

    def release(self):
        pass


def _fake_picamera2(metadata):
    class Picamera2:
        camera_properties = {"Model": "fake"}

        def create_video_configuration(self, **kw):
            return kw

        def configure(self, config):
            pass

        def start(self):
            pass

        def capture_request(self):
            return _Request(metadata)

        def stop(self):
            pass

        def close(self):
            pass

    return types.SimpleNamespace(Picamera2=Picamera2)


def test_pi_camera_stamp_is_sensor_start_plus_half_the_exposure(monkeypatch):
    start_ns = time.monotonic_ns() - 20_000_000  # exposure began 20 ms ago
    metadata = {"SensorTimestamp": start_ns, "ExposureTime": 10000}  # µs
    monkeypatch.setitem(sys.modules, "picamera2", _fake_picamera2(metadata))
    src = Picamera2Source(SourceConfig(kind="picamera2", width=64, height=64))
    src.open()
    try:
        _, t_ns = src.read()
    finally:
        src.close()
    # the sensor clock is the agent's clock here, so the only difference is half of 10 ms (the 1 ms margin
    # is for a preemption between the source's two clock reads)
    assert abs(t_ns - (start_ns + 5_000_000)) < 1_000_000


def test_mid_exposure_offset():
    assert mid_exposure_offset_ns(2000) == 1_000_000
    assert mid_exposure_offset_ns(None) == 0
    assert mid_exposure_offset_ns(0) == 0
