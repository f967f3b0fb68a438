"""One settings model for every process.

Every address, port and tunable comes from :class:`Settings`: environment variables with
the ``SEMSERVO_`` prefix, nested fields joined with ``__`` (for example
``SEMSERVO_IMAGESERVER__FPS=5``). Defaults bind and connect on loopback, so the same code
runs as processes on one PC; on two PCs or in containers only ``bind_host`` and the
``*.host`` fields change (see ``deploy/two-pc.md``).
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, Field, PositiveFloat, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from semservo.protocol.estimator import FocusMeasure

#: Screen size constant of the paper's SEM: P = D / G (eq. 43) with D = 212.3 um for a
#: 512-pixel-wide image, G the magnification.
SCREEN_WIDTH_UM = 212.3
SCREEN_WIDTH_PX = 512
#: The pixel sizes a picture as the fake lab's sample may have (nm): the finest SEMs
#: resolve about 0.1 nm, and at far finer pixels the simulated probe spans so many pixels
#: that frames stall; the coarsest is a 1024 px field of 1 m.
SAMPLE_PIXEL_NM_RANGE = (0.01, 1e6)

RECORDED_RUN_NAME = "sem-run-2013"
SEM_IMAGES_NAME = "sem-images"


def pixel_size_nm(magnification: float, width_px: int = SCREEN_WIDTH_PX) -> float:
    """Pixel size on the sample in nanometres, P = D / G (paper eq. 43).

    D is the screen width (212.3 um for 512 pixels on the paper's system); an image
    that is ``width_px`` wide spreads the same field over more or fewer pixels.
    """
    if magnification <= 0:
        raise ValueError(f"magnification must be positive, got {magnification}")
    return SCREEN_WIDTH_UM * 1e3 / magnification * SCREEN_WIDTH_PX / width_px


def _find_shared_data(name: str, marker: str) -> Path:
    """``<repo>/../shared/data/<name>``: looked up beside the checkout (the workplace
    keeps ``shared/`` next to it) and, failing that, beside the current directory. The
    data is never copied into the repository."""
    here = Path(__file__).resolve()
    cwd = Path.cwd().resolve()
    candidates = [parent.parent / "shared" / "data" / name for parent in (*here.parents, cwd, *cwd.parents)]
    for candidate in candidates:
        if (candidate / marker).is_file():
            return candidate
    # Not found: return the conventional place so error messages name it.
    return here.parents[2].parent / "shared" / "data" / name


def find_recorded_run() -> Path:
    """Where the real 2013 recording lies: ``<repo>/../shared/data/sem-run-2013``
    (``SEMSERVO_IMAGESERVER__REPLAY_DIR`` points elsewhere)."""
    return _find_shared_data(RECORDED_RUN_NAME, "reference.png")


def find_sem_images() -> Path:
    """Where the real SEM images of other instruments lie:
    ``<repo>/../shared/data/sem-images`` (``SEMSERVO_SEM_IMAGES`` points elsewhere)."""
    return Path(os.environ.get("SEMSERVO_SEM_IMAGES") or _find_shared_data(SEM_IMAGES_NAME, "README.md"))


def _integer_text(value):
    """An environment variable is text: "-1" is the sign -1."""
    if isinstance(value, str):
        try:
            return int(value.strip())
        except ValueError:
            return value
    return value


#: A sign, +1 or -1 (from an environment variable as well as from JSON).
Sign = Annotated[Literal[-1, 1], BeforeValidator(_integer_text)]


class ImageServerSettings(BaseModel):
    """The image server: where it publishes frames and which source it reads."""

    host: str = Field("127.0.0.1", description="address other services connect to")
    frames_port: int = Field(5550, ge=1, le=65535, description="PUB socket for frames")
    control_port: int = Field(5551, ge=1, le=65535, description="REP socket for commands and health")
    source: Literal["sim", "replay", "watch", "adapter"] = Field(
        "sim", description="sim: the fake lab's SEM; replay: a folder, again and again; watch: the folder an SEM "
                           "saves its frames into; adapter: a lab's own source (see adapter)")
    replay_dir: Path = Field(default_factory=find_recorded_run, description="folder of PNG/TIFF frames")
    replay_glob: str | None = Field(None, description="which files of the folder to replay, e.g. 'frame*' (by default "
                                                      "every PNG/TIFF but a reference.*: the taught image a "
                                                      "recording keeps beside its frames)")
    fps: PositiveFloat = Field(10.0, le=10_000, description="frames published per second (replay, sim)")
    loop: bool = Field(True, description="replay again from the first frame at the end")
    watch_dir: Path | None = Field(None, description="watch: the folder the SEM's software saves frames into")
    watch_glob: str = Field("*", description="watch: which files are frames, e.g. '*.tif'")
    watch_existing: bool = Field(False, description="watch: also publish the files already there at start")
    watch_settle_s: PositiveFloat = Field(0.3, le=60, description="watch: without a close event, a file is "
                                                                  "complete once unchanged this long")
    watch_give_up_s: PositiveFloat = Field(10.0, le=3600, description="watch: longest an unfinished file holds "
                                                                      "the ones after it")
    watch_polling: bool = Field(False, description="watch: poll the folder instead of OS events (network shares)")
    adapter: str | None = Field(None, description="adapter: an entry point of semservo.image_sources or "
                                                  "package.module:ClassName (semservo.instruments.ImageSourceAdapter)")
    adapter_options: dict[str, Any] = Field(default_factory=dict, description="adapter: its keyword arguments")
    data_bar: Literal["auto"] | Annotated[int, Field(ge=0, le=100_000)] = Field(
        "auto", description="rows of data bar to crop from files: auto (the metadata, else detected), or a number")
    # What to assume when the files (replay, watch) do not say; unset: unknown, never made up.
    magnification: PositiveFloat | None = Field(None, description="magnification when a file does not say")
    pixel_size_nm: PositiveFloat | None = Field(None, description="pixel size when a file does not say; "
                                                                  "unset with a magnification given: P = D / G (eq. 43)")
    dwell_ns: PositiveFloat | None = Field(None, description="dwell time per pixel when a file does not say")
    scan_dwell_ns: PositiveFloat | None = Field(None, description="sim: dwell to request (default: the preset's)")
    scan_magnification: PositiveFloat | None = Field(None, description="sim: magnification to request")
    scan_working_distance_um: float | None = Field(None, description="sim: focus, the working distance's offset from the stage's reference surface in um, larger deeper (default: the preset's, the part's top)")
    scan_aperture_um: float | None = Field(None, ge=5, le=2000, description="sim: objective aperture diameter, um "
                                                                     "(default: the preset's; sets the depth of field)")
    scan_brightness: float = Field(0.0, ge=-1, le=1, description="sim: offset, fraction of full scale")
    scan_contrast: float = Field(1.0, gt=0, le=10, description="sim: gain")
    scan_bit_depth: Literal[8, 16] = Field(8, description="sim: 8- or 16-bit frames")
    scan_timeout_s: PositiveFloat = Field(10.0, description="sim: give up on a scan after this long")


class FakelabSettings(BaseModel):
    """The simulated lab: an emulated NV 40/3 and a simulated SEM in one world."""

    host: str = Field("127.0.0.1", description="address other services connect to")
    control_port: int = Field(5590, ge=1, le=65535, description="REP socket for commands, health, true pose")
    scan_port: int = Field(5591, ge=1, le=65535, description="REP socket the image server asks for frames")
    serial_tcp_port: int = Field(5592, ge=1, le=65535, description="the NV 40/3 on TCP (socket://)")
    serial_bind_host: str | None = Field(
        None, description="interface the NV 40/3's TCP port binds to (default: bind_host); in containers its "
                          "address on the serial network alone, so only the stage service reaches the amplifier")
    preset: str = Field("optimal", description="one of the paper's conditions (semservo.simulation.world.PRESETS)")
    speedup: PositiveFloat = Field(1.0, le=1000, description="simulated time runs this many times faster")
    seed: int = 2013
    save_frames_dir: Path | None = Field(None, description="also scan continuously and save every frame here, as "
                                                           "an SEM's software does (FEI-style TIFF with a data bar)")
    save_chunks: int = Field(4, ge=1, le=1000, description="each saved file is written in this many pieces")
    save_chunk_pause_s: float = Field(0.01, ge=0, le=10, description="pause between the pieces")
    save_interval_s: float = Field(0.1, ge=0, le=3600, description="a frame saved this often at most (wall time)")
    save_keep: int | None = Field(200, ge=1, le=10_000_000, description="keep the last this many saved frames, "
                                                                        "deleting the older ones it saved (null: all)")
    # A real SEM image as the sample (semservo.simulation.sample_image), under the preset's optics.
    sample_image: Path | None = Field(None, description="a real SEM image (PNG/TIFF, 8/16 bit) as the sample instead "
                                                        "of the preset's scene; its data bar is cropped")
    sample_pixel_size_nm: float | None = Field(None, ge=SAMPLE_PIXEL_NM_RANGE[0], le=SAMPLE_PIXEL_NM_RANGE[1],
                                               description="the sample image's pixel size "
                                                       "(default: its file's metadata; required when the file has none)")
    sample_data_bar: Literal["auto"] | Annotated[int, Field(ge=0, le=100_000)] = Field(
        "auto", description="rows of data bar to crop from the sample image: auto (metadata, else detected) or a number")
    sample_height_image: Path | None = Field(None, description="a height map of the sample image's field (brighter "
                                                               "is higher, towards the lens); none: flat")
    sample_height_um: PositiveFloat | None = Field(None, le=1e4, description="the height map's brightest level over "
                                                   "its darkest, um (required with a height map)")
    sample_edges: Literal["mirror", "tile", "pad"] = Field(
        "mirror", description="the sample beyond the image's edges: mirrored (no seam), tiled (a seam, periodic) or "
                              "padded with its median grey (flat)")
    sample_denoise: float = Field(1.5, ge=0, le=10, description="remove the image's own noise before imaging it again: "
                                                                "non-local means at this many times its estimated "
                                                                "deviation (0: keep it)")
    sample_max_upsampling: float = Field(2.0, ge=1, le=100, description="refuse scans whose pixel is more than this "
                                                                        "many times finer than the sample image's")
    sample_max_field: float = Field(1.0, gt=0, le=100, description="refuse scans whose field is more than this many "
                                                                   "times the sample image's (either axis)")


class EstimatorSettings(BaseModel):
    """The estimator: frames in (from the image server), motion out."""

    host: str = Field("127.0.0.1", description="address other services connect to")
    motion_port: int = Field(5560, ge=1, le=65535, description="PUB socket for motion estimates")
    control_port: int = Field(5561, ge=1, le=65535, description="REP socket for commands and health")
    rotation: bool = Field(True, description="estimate rotation about the beam too")
    precision: Literal["fast", "full"] = Field("full", description="sub-pixel fit at full resolution (default) or on the 2x search pair")
    scan_averaged: bool = Field(True, description="average each shift over the scan's bands of rows (vibration faster "
                                                  "than a frame draws each band at its own offset; "
                                                  "semservo.estimation.raster); off: the whole-frame estimate")
    vibration_lines: bool = Field(True, description="learn the stage's vibration lines (steady tones) from the frames "
                                                    "at rest when a frame is taught, and fit them in each scan-averaged "
                                                    "shift; off (or none learned): the bands' mean. Off for a vibration "
                                                    "that is not steady tones (a phase wandering a radian a scan)")
    fft_effort: Literal["FFTW_ESTIMATE", "FFTW_MEASURE", "FFTW_PATIENT"] = "FFTW_MEASURE"
    tilt_method: Literal["plane", "egi"] = Field(
        "plane", description="tilts from the focus sweep: a robust plane fit (default) or the paper's EGI correlation")
    tilt_depth_of_field_um: float = Field(
        3.5, gt=0, le=1e4, description="the SEM's depth of field for the tilt sweeps (2 P / beam half-angle): sets "
                                       "their step; the fake lab's tilts preset: 3.5 um")
    tilt_centre_um: float = Field(0.0, ge=-1e4, le=1e4, description="working distance offset (um) the first sweep is "
                                                                    "centred on: where the taught view is in focus")
    tilt_max_deg: float = Field(15.0, gt=0, le=45, description="the first sweep is wide enough for this much tilt")
    tilt_kernel_px: int = Field(32, ge=8, le=256, description="kernel size of the focus measure (eq. 13)")
    tilt_focus_measure: FocusMeasure = Field(
        "normalized_variance", description="the focus measure each kernel's focus curve is read by: eq. 13's normalized "
                                           "variance (the paper's), or gradient: the gradient energy over the mean, "
                                           "which pins the tilts of sparse textures more tightly (bench/tilt_bounds.py)")
    tilt_teach_sweeps: int = Field(4, ge=1, le=16, description="the most focus sweeps a teach with tilts takes of the "
                                                               "taught pose, pooled, while they pin the tilts loosely")
    tilt_fine_teach_sweeps: int = Field(8, ge=0, le=16,
                                        description="where those cannot pin the tilts, the most fine sweeps (a quarter "
                                                    "of a depth of field apart, about the depths they found) the teach "
                                                    "takes instead (0: none, the teach refused there)")
    sweep_timeout_s: float = Field(120.0, gt=0, le=3600, description="a focus sweep that takes longer has failed")


class StageSettings(BaseModel):
    """The stage service: the NV 40/3 on its serial link, and its safety limits."""

    host: str = Field("127.0.0.1", description="address other services connect to")
    control_port: int = Field(5570, ge=1, le=65535, description="REP socket for moves, stop, state, health")
    driver: str = Field("nv40", description="stage driver: nv40, simulated (in-process, no hardware), "
                                            "openfibsem (a microscope's stage and beam shift, semservo[openfibsem]), "
                                            "simulated-positioner, an entry point of semservo.stage_drivers or "
                                            "package.module:ClassName")
    serial_url: str = Field("socket://127.0.0.1:5592",
                            description="the driver's link: a pyserial URL (/dev/ttyUSB0, a pseudo-terminal path or "
                                        "socket://host:port); openfibsem://MANUFACTURER@HOST for openfibsem")
    axes: dict[str, int] = Field(default_factory=lambda: {"x": 0, "y": 1}, description="axis name -> NV 40/3 channel")
    model_files: dict[str, str] = Field(default_factory=dict,
                                        description="axis -> displacement model JSON (stage_model.save_model); default TRITOR")
    voltage_min: float = Field(-19.0, ge=-20, le=130, description="soft lower voltage limit (the lab's)")
    voltage_max: float = Field(110.0, ge=-20, le=130, description="soft upper voltage limit (the lab's)")
    travel_min_um: float = Field(0.0, description="soft travel limit, model displacement")
    travel_max_um: float = Field(100.0, description="soft travel limit, model displacement")
    max_step_v: PositiveFloat = Field(25.0, le=150, description="largest voltage change one command may ask")
    max_rate_v_per_s: PositiveFloat = Field(200.0, description="fastest voltage change between commands")
    state_dir: Path = Field(Path("runs"), description="what outlives the process: whether a run had the stage "
                                                      "armed (stage-state.json) and the command log (stage-commands.jsonl)")
    rotation_stage: Literal["none", "fakelab"] = Field(
        "fakelab", description="the rotation-and-tilt stage this service drives: the fake lab's simulated one, or none")
    max_turn_deg: PositiveFloat = Field(30.0, le=360, description="largest turn or tilt one command may ask (degrees)")
    settle_s: dict[str, Annotated[float, Field(ge=0, le=60)]] = Field(
        default_factory=dict, description="axis -> seconds the axis takes to settle after a move (default 0.01): a "
                                          "frame scanned before then shows it moving")
    # A motion driver in physical units (a closed-loop stage, a microscope's stage and beam
    # shift through OpenFIBSEM): the same rules, per axis, in micrometres and degrees.
    max_step_um: PositiveFloat = Field(10.0, le=10_000, description="physical axes: largest displacement one "
                                                                    "command may ask (um; degrees: max_turn_deg)")
    max_steps: dict[str, PositiveFloat] = Field(default_factory=dict, description="physical axes: axis -> its own "
                                                                                  "largest step (um or degrees)")
    travel: dict[str, tuple[float, float]] = Field(
        default_factory=dict, description="physical axes: axis -> [min, max], the lab's travel (the device's "
                                          "coordinates), within the device's own")
    readback_tolerance: dict[str, PositiveFloat] = Field(
        default_factory=dict, description="physical axes: axis -> read-back change that counts as a move nobody "
                                          "commanded (default 0.2 um stage, 0.01 um beam, 0.01 degree)")
    arrival_tolerance: dict[str, PositiveFloat] = Field(
        default_factory=dict, description="physical axes: axis -> farthest from its goal a move may arrive "
                                          "(default 0.5 um stage, 0.01 um beam, 0.05 degree)")


class ControllerSettings(BaseModel):
    """The controller: motion estimates in, stage moves out (eq. 30-37)."""

    host: str = Field("127.0.0.1", description="address other services connect to")
    control_port: int = Field(5580, ge=1, le=65535, description="REP socket for start, stop, status, runs")
    status_port: int = Field(5581, ge=1, le=65535, description="PUB socket: status and per-iteration records")
    runs_dir: Path = Field(Path("runs"), description="where run records (JSON) are written")
    watchdog_s: PositiveFloat = Field(3.0, le=600, description="the stage holds if the controller is silent this long")
    axis_signs: tuple[Sign, Sign] = Field(
        (1, 1), description="camera-to-stage: +1 if stage +x/+y moves content right/down")
    orientation_deg: float = Field(0.0, ge=-360, le=360, description="camera-to-stage: stage x axis in the image, "
                                                                     "counter-clockwise")
    rotation_sign: Sign = Field(1, description="camera-to-stage: +1 if a positive turn of the rotation "
                                                         "stage turns the content counter-clockwise")
    tilt_signs: tuple[Sign, Sign] = Field(
        (1, 1), description="camera-to-stage: +1 if a positive stage tilt about x / y tilts the surface by +alpha / "
                            "+beta (semservo.estimation.tilt's convention)")

    def camera_to_stage(self):
        """The camera-to-stage transform these settings describe: the one every part that
        turns image motion into stage motion uses (the controller, the gateway's
        click-to-move, ``semservo calibrate``)."""
        from semservo.control import CameraToStage

        return CameraToStage(tuple(self.axis_signs), self.orientation_deg, self.rotation_sign, tuple(self.tilt_signs))


class GatewaySettings(BaseModel):
    """The REST gateway (FastAPI on uvicorn): the one door for scripts and the dashboard."""

    host: str = Field("127.0.0.1", description="address other processes reach it at")
    http_host: str = Field("127.0.0.1", description="HTTP address to bind; anything but loopback needs api_token")
    http_port: int = Field(8000, ge=1, le=65535, description="HTTP port: the API, its docs and the dashboard")
    control_port: int = Field(5585, ge=1, le=65535, description="REP socket for health (the launcher's)")
    api_token: SecretStr | None = Field(None, description="bearer token for state-changing endpoints")
    database: Path = Field(Path("runs/semservo.sqlite"), description="SQLite file with every run's record")
    save_frames: bool = Field(False, description="also keep each run's frames as TIFF (frames/<run id>/ beside the database)")
    max_upload_bytes: int = Field(32 * 2**20, ge=1024, description="largest image upload accepted")


class Settings(BaseSettings):
    """Everything a semservo process needs to know about its place in the system."""

    model_config = SettingsConfigDict(env_prefix="SEMSERVO_", env_nested_delimiter="__", extra="ignore")

    bind_host: str = Field("127.0.0.1", description="interface services bind to (0.0.0.0 in containers)")
    max_message_bytes: int = Field(64 * 2**20, ge=1024, description="larger messages are dropped and counted")
    request_timeout_s: PositiveFloat = Field(1.0, description="lazy-pirate timeout per try")
    request_retries: int = Field(3, ge=1, description="lazy-pirate tries before a service counts as down")
    curve_keys_dir: Path | None = Field(
        None, description="CURVE keys (semservo keys DIR): every ZeroMQ socket authenticated and encrypted; "
                          "required when any socket leaves loopback")
    log_level: str = "INFO"
    fakelab: FakelabSettings = Field(default_factory=FakelabSettings)
    imageserver: ImageServerSettings = Field(default_factory=ImageServerSettings)
    estimator: EstimatorSettings = Field(default_factory=EstimatorSettings)
    stage: StageSettings = Field(default_factory=StageSettings)
    controller: ControllerSettings = Field(default_factory=ControllerSettings)
    gateway: GatewaySettings = Field(default_factory=GatewaySettings)

    def bind(self, port: int) -> str:
        return f"tcp://{self.bind_host}:{port}"


def unrecognised_settings(environ=None) -> list[str]:
    """What is wrong with each SEMSERVO_<SECTION>__<NAME> variable (``environ``, default
    the process's) that names no setting of its section, with the closest names. The
    settings ignore unknown names, so a misspelt one (``SEMSERVO_FAKELAB__SAMPLE_PIXEL_NM``)
    would silently do nothing; ``semservo up`` and ``demo`` say so instead."""
    import difflib

    environ = os.environ if environ is None else environ
    problems = []
    for variable in sorted(environ):
        upper = variable.upper()
        if not upper.startswith("SEMSERVO_") or "__" not in upper:
            continue
        section, _, rest = upper[len("SEMSERVO_"):].partition("__")
        field = Settings.model_fields.get(section.lower())
        model = field.annotation if field is not None else None
        if not (isinstance(model, type) and issubclass(model, BaseModel)):
            continue
        name = rest.partition("__")[0].lower()
        if name in model.model_fields:
            continue
        close = difflib.get_close_matches(name, list(model.model_fields), n=2, cutoff=0.6)
        names = " or ".join(f"SEMSERVO_{section}__{match.upper()}" for match in close)
        hint = f"; did you mean {names}?" if close else ""
        problems.append(f"{variable} names no setting of {section.lower()}, so it does nothing{hint}")
    return problems


def connect(host: str, port: int) -> str:
    """ZeroMQ address a client connects to."""
    return f"tcp://{host}:{port}"


@lru_cache(maxsize=1)
def settings_from_environment() -> Settings:
    return Settings()
