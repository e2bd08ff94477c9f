"""Live capture from a Luxonis OAK (depthai v3): colour + stereo depth aligned to colour, as RGBDFrame.

depthai is imported here only when a camera is used. Before any pipeline is built, the connected devices
are listed with ``dai.Device.getAllAvailableDevices()`` (it answers at once; opening a pipeline with no
device makes depthai 3.12 wait about 11 s and then raise a bare ``RuntimeError``), in a helper thread
bounded by ``timeout_s``, so that with no camera the caller gets :class:`DeviceNotFoundError` within seconds.

Pipeline: ``Camera`` CAM_A (colour, RGB888 interleaved at the depth size) and ``StereoDepth.build(
autoCreateCameras=True, preset)`` (the mono pair on CAM_B / CAM_C) with depth aligned to CAM_A;
intrinsics from the device calibration for CAM_A at the output size. The close-range default is the
``HIGH_DETAIL`` preset with extended disparity (minimum range about 35 cm at 640 x 400 -> 20 cm).
With ``record_to`` set, depthai's holistic recording (``Pipeline.enableHolisticRecord``) also writes its
own replayable recording of the session to that folder.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Self

import numpy as np

from perception.camera.frame import Intrinsics, RGBDFrame
from perception.errors import DeviceNotFoundError

log = logging.getLogger(__name__)

#: What to tell a user without a camera.
NO_DEVICE_HINT = (
    "connect an OAK over USB, or replay a recording instead: "
    "`visuotactile camera --source <recording folder>` (colour PNG + 16-bit depth PNG + JSON), "
    "or simulate one with `--source virtual:<class>`"
)


def _import_depthai():
    try:
        import depthai as dai
    except ImportError as exc:
        raise DeviceNotFoundError(
            f"OAK camera: depthai is not installed ({exc}); install the camera extra "
            f"(pip install 'visuotactile[camera]'), or {NO_DEVICE_HINT}"
        ) from None
    return dai


def find_oak_devices(timeout_s: float = 3.0) -> list:
    """The OAK devices depthai can see now (``DeviceInfo`` list), answering within ``timeout_s``.

    Raises:
        DeviceNotFoundError: depthai is missing, or the device search did not answer in time.
    """
    dai = _import_depthai()
    found: dict = {}

    def search() -> None:
        try:
            found["devices"] = list(dai.Device.getAllAvailableDevices())
        except Exception as exc:  # noqa: BLE001 - reported below as "no device"
            found["error"] = exc

    thread = threading.Thread(target=search, name="oak-device-search", daemon=True)
    thread.start()
    thread.join(timeout_s)
    if thread.is_alive():
        raise DeviceNotFoundError(f"OAK camera: the device search did not answer within {timeout_s:g} s; {NO_DEVICE_HINT}")
    if "error" in found:
        raise DeviceNotFoundError(f"OAK camera: the device search failed ({found['error']}); {NO_DEVICE_HINT}")
    return found["devices"]


class OakCamera:
    """A live OAK-D giving :class:`RGBDFrame` s; use as a context manager (closes on exit, Ctrl-C included).

    Args:
        size: output (width, height) of colour and depth, px.
        preset: ``StereoDepth.PresetMode`` name (``HIGH_DETAIL``, ``DEFAULT``, ``ROBOTICS``, ...).
        extended_disparity: halve the minimum range (close objects).
        fps: camera frame rate.
        device_id: a specific device (``DeviceInfo.deviceId``), else the first found.
        record_to: folder for depthai's holistic recording of the session, or None.
        timeout_s: limit for the device search and for each frame, s.

    Raises:
        DeviceNotFoundError: (on ``open``/``with``) depthai missing, no device, or it cannot be opened.
    """

    def __init__(
        self,
        size: tuple[int, int] = (640, 400),
        *,
        preset: str = "HIGH_DETAIL",
        extended_disparity: bool = True,
        fps: float = 15.0,
        device_id: str | None = None,
        record_to: str | Path | None = None,
        timeout_s: float = 3.0,
    ) -> None:
        self.size = (int(size[0]), int(size[1]))
        self.preset = preset
        self.extended_disparity = extended_disparity
        self.fps = fps
        self.device_id = device_id
        self.record_to = record_to
        self.timeout_s = timeout_s
        self._pipeline = None
        self._queues = None
        self.intrinsics: Intrinsics | None = None

    # ------------------------------------------------------------------------------ life cycle
    def open(self) -> OakCamera:
        """Find the device, build and start the pipeline.

        Raises:
            DeviceNotFoundError: depthai missing, no device found, or the device could not be opened.
        """
        devices = find_oak_devices(self.timeout_s)
        if self.device_id is not None:
            devices = [d for d in devices if getattr(d, "deviceId", None) == self.device_id]
        if not devices:
            wanted = f" with id {self.device_id}" if self.device_id else ""
            raise DeviceNotFoundError(f"OAK camera: no device{wanted} found; {NO_DEVICE_HINT}")
        dai = _import_depthai()
        try:
            device = dai.Device(devices[0])
            pipeline = dai.Pipeline(device)
            color = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
            color_out = color.requestOutput(self.size, dai.ImgFrame.Type.RGB888i, fps=self.fps)
            preset = getattr(dai.node.StereoDepth.PresetMode, self.preset)
            stereo = pipeline.create(dai.node.StereoDepth).build(True, preset, self.size, self.fps)
            stereo.setExtendedDisparity(self.extended_disparity)
            stereo.setDepthAlign(dai.CameraBoardSocket.CAM_A)
            stereo.setOutputSize(*self.size)
            if self.record_to is not None:
                config = dai.RecordConfig()
                config.outputDir = str(self.record_to)
                pipeline.enableHolisticRecord(config)
            self._queues = (
                color_out.createOutputQueue(maxSize=4, blocking=False),
                stereo.depth.createOutputQueue(maxSize=4, blocking=False),
            )
            calib = device.readCalibration()
            k = np.asarray(calib.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, *self.size))
            self.intrinsics = Intrinsics.from_matrix(k, *self.size)
            pipeline.start()
        except DeviceNotFoundError:
            raise
        except (RuntimeError, OSError, ValueError) as exc:  # depthai's device problems are RuntimeErrors
            self.close()
            raise DeviceNotFoundError(f"OAK camera: cannot open the device ({exc}); {NO_DEVICE_HINT}") from None
        self._pipeline = pipeline
        log.info("OAK camera open: %s, %d x %d, preset %s", devices[0], *self.size, self.preset)
        return self

    def close(self) -> None:
        """Stop the pipeline (safe to call twice)."""
        pipeline, self._pipeline, self._queues = self._pipeline, None, None
        if pipeline is not None:
            try:
                pipeline.stop()
            except Exception as exc:  # noqa: BLE001 - closing must not raise over the real error
                log.warning("OAK camera: stopping the pipeline failed: %s", exc)

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # --------------------------------------------------------------------------------- frames
    def capture(self, pose: np.ndarray | None = None) -> RGBDFrame:
        """The next colour + depth pair as an :class:`RGBDFrame` (``pose``: camera-to-world, if known).

        Raises:
            DeviceNotFoundError: the camera is not open, or no frame arrived within ``timeout_s``.
        """
        if self._pipeline is None or self._queues is None:
            raise DeviceNotFoundError("OAK camera: not open; use `with OakCamera() as cam:` or call open()")
        color_q, depth_q = self._queues
        deadline = time.monotonic() + self.timeout_s
        color = depth = None
        while (color is None or depth is None) and time.monotonic() < deadline:
            new_color, new_depth = color_q.tryGet(), depth_q.tryGet()
            color = new_color if new_color is not None else color
            depth = new_depth if new_depth is not None else depth
            if color is None or depth is None:
                time.sleep(0.005)
        if color is None or depth is None:
            raise DeviceNotFoundError(f"OAK camera: no frame within {self.timeout_s:g} s; is the device still connected?")
        rgb = np.asarray(color.getFrame(), dtype=np.uint8).reshape(self.size[1], self.size[0], 3)
        depth_mm = np.asarray(depth.getFrame(), dtype=np.float32)
        return RGBDFrame(
            rgb, depth_mm, self.intrinsics, np.eye(4) if pose is None else pose,
            timestamp_s=depth.getTimestamp().total_seconds(), name=f"oak:{self.device_id or 'default'}",
        )

    def frames(self, n: int) -> list[RGBDFrame]:
        """``n`` consecutive frames."""
        return [self.capture() for _ in range(n)]


__all__ = ["NO_DEVICE_HINT", "OakCamera", "find_oak_devices"]
