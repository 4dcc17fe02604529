"""One exception root: every user-facing error is a VisionposError, and keeps the base its callers catch."""

from __future__ import annotations

import pytest

from bridge.transport import LinkDown
from stations.sources import EndOfStream, SourceError
from visionpos.analysis.plots import PlotsUnavailable
from visionpos.calibration.pairwise import DegenerateMotion
from visionpos.calibration.wand import CalibrationError
from visionpos.camera.model import CameraModelError
from visionpos.config.arena import ConfigError, parse_arena
from visionpos.errors import UsageError, VisionposError
from visionpos.protocol import ProtocolError
from visionpos.recording import RecordingError

# error class -> the base that code catching it before the root existed still relies on
USER_FACING = {
    UsageError: VisionposError,
    ConfigError: ValueError,  # visionpos/cli.py: `except ValueError`
    ProtocolError: ValueError,
    RecordingError: ValueError,
    CalibrationError: ValueError,  # calibration/pairwise.py: `except (CalibrationError, ValueError)`
    DegenerateMotion: CalibrationError,
    CameraModelError: ValueError,  # config/arena.py re-raises it as a ConfigError
    SourceError: RuntimeError,
    PlotsUnavailable: ImportError,  # analysis/replay.py: `except ImportError` (plots extra missing)
}


@pytest.mark.parametrize("cls", list(USER_FACING), ids=lambda c: c.__name__)
def test_user_facing_errors_share_the_root_and_keep_their_base(cls):
    assert issubclass(cls, VisionposError)
    assert issubclass(cls, USER_FACING[cls])


@pytest.mark.parametrize("cls", [LinkDown, EndOfStream], ids=lambda c: c.__name__)
def test_runtime_signals_are_not_user_errors(cls):
    # LinkDown: the bridge closes and reopens the link; EndOfStream: a file source ran out. Neither reaches a user.
    assert not issubclass(cls, VisionposError)


def test_a_bad_config_is_caught_as_a_visionpos_error():
    with pytest.raises(VisionposError) as info:
        parse_arena({"cameras": "not a list"}, "bad.yaml")
    assert isinstance(info.value, ConfigError) and "bad.yaml" in str(info.value)
