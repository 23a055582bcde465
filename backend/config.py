"""The back-end's configuration schema: every section, key, default and allowed range.

`config/backend.toml` mirrors these defaults; `tests/test_backend_config.py` keeps the two in step.
Environment overrides use the prefix `CLOUDTRACK_BACKEND_` (e.g. `CLOUDTRACK_BACKEND_SERVER__PORT=9000`)
so that the companion's own `CLOUDTRACK_<SECTION>__<KEY>` variables never reach this schema.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from cloudtrack.config_files import ConfigSection, default_config_files, load_config
from cloudtrack.cursor_on_target import check_url

ENV_PREFIX = "CLOUDTRACK_BACKEND_"
CONFIG_FILE_NAME = "backend.toml"  # looked up in /etc/cloudtrack/ and $XDG_CONFIG_HOME/cloudtrack/

DetectorKind = Literal["yolox", "deimv2_atto", "deimv2_femto", "grounding_dino", "owlv2", "simulated"]
VerifierKind = Literal["none", "local", "local-hsv", "vlm", "cascade"]
UncertainPolicy = Literal["uncertain", "yes", "no"]


class ServerConfig(ConfigSection):
    host: str = "127.0.0.1"  # behind a TLS reverse proxy; see docs/backend.md
    port: int = Field(8080, ge=1, le=65535)
    max_request_bytes: int = Field(2_000_000, ge=10_000, le=100_000_000)
    max_image_pixels: int = Field(16_000_000, ge=10_000, le=100_000_000)  # decompression-bomb guard
    # A crop (rejection, supervisor's candidate) is a small image: 4 Mpx is generous.
    max_crop_pixels: int = Field(4_000_000, ge=10_000, le=100_000_000)
    # A request body must arrive within this time (a body that never completes is cut off with 408).
    body_timeout_s: float = Field(15.0, gt=0, le=600)
    # The request line and headers must arrive within this time of the connection (or of the previous
    # answer on a kept-alive one); a client trickling header lines is answered 408 and disconnected.
    header_timeout_s: float = Field(10.0, gt=0, le=600)


MIN_TOKEN_CHARS = 16


class AuthConfig(ConfigSection):
    # vehicle id -> bearer token. Prefer CLOUDTRACK_BACKEND_AUTH__TOKENS='{"drone-1": "..."}'.
    # Every token: at least 16 characters, one per vehicle, none equal to the supervisor's.
    tokens: dict[str, str] = Field(default_factory=dict)
    # Token of the supervisor web page and API. Empty (the default): the supervisor endpoints are off and
    # the page says how to turn them on, instead of asking for a token that does not exist.
    supervisor_token: str = ""

    # Errors below name vehicles, never tokens: a config error must not print a secret.
    @field_validator("tokens", mode="before")
    @classmethod
    def _tokens_as_text(cls, value: object) -> object:
        # An all-digit token in JSON is still a token.
        if isinstance(value, dict):
            return {
                k: str(v) if isinstance(v, int) and not isinstance(v, bool) else v for k, v in value.items()
            }
        return value

    @field_validator("supervisor_token", mode="before")
    @classmethod
    def _supervisor_as_text(cls, value: object) -> object:
        return str(value) if isinstance(value, int) and not isinstance(value, bool) else value

    @model_validator(mode="after")
    def _strong_and_distinct(self) -> AuthConfig:
        problems = []
        short = sorted(v for v, t in self.tokens.items() if len(t) < MIN_TOKEN_CHARS)
        if short:
            problems.append(f"tokens of {', '.join(short)} are shorter than {MIN_TOKEN_CHARS} characters")
        if self.supervisor_token and len(self.supervisor_token) < MIN_TOKEN_CHARS:
            problems.append(f"supervisor_token is shorter than {MIN_TOKEN_CHARS} characters")
        by_token: dict[str, list[str]] = {}
        for vehicle, token in self.tokens.items():
            by_token.setdefault(token, []).append(vehicle)
        for vehicles in by_token.values():
            if len(vehicles) > 1:
                problems.append(f"vehicles {', '.join(sorted(vehicles))} share one token")
        same = sorted(
            v for v, t in self.tokens.items() if self.supervisor_token and t == self.supervisor_token
        )
        if same:
            problems.append(f"the token of {', '.join(same)} equals supervisor_token")
        if problems:
            raise ValueError("; ".join(problems) + " (generate tokens with: openssl rand -hex 24)")
        return self


class DetectorConfig(ConfigSection):
    # yolox (YOLOX-nano), deimv2_atto / deimv2_femto (DEIMv2, same classes, tiling and threshold; measured
    # side by side in docs/tracking.md, "Superset detectors"), grounding_dino / owlv2 (open vocabulary, gpu extra).
    kind: DetectorKind = "yolox"
    model_dir: str = ""  # empty: $CLOUDTRACK_MODEL_DIR, then the user cache
    # 0.2: the detector proposes, the verifier judges; a target never proposed can never be chosen. YOLOX-nano
    # scores targets between its classes (a van, a bag COCO has no class for) 0.2-0.3: recall at 0.2 rises in
    # every size class for about one more box per keyframe to verify (docs/benchmarks.md, "Back-end detection").
    score_threshold: float = Field(0.2, ge=0, le=1)
    nms_threshold: float = Field(0.45, gt=0, le=1)
    # onnxruntime intra-op threads per detection (0: all cores). One thread and `sessions.detector_concurrency`
    # detections in parallel uses the cores best under load; more threads lower one frame's latency on an idle CPU.
    threads: int = Field(1, ge=0, le=64)
    # Hugging Face model id or local folder for grounding_dino / owlv2.
    hf_model: str = ""
    device: str = "cpu"  # torch device for grounding_dino / owlv2, e.g. "cuda"
    max_candidates: int = Field(10, ge=1, le=100)
    # yolox weights: "fp32" (the shared model) or "int8" (<model_dir>/yolox_nano/yolox_nano_int8.onnx, made by
    # `python -m backend_tools.quantize`). fp32 by default: int8 lost recall and was no faster here.
    precision: Literal["fp32", "int8"] = "fp32"
    # Sliced inference for small targets: the whole frame plus a grid of `tiles` columns (rows follow the
    # frame's aspect ratio) overlapping by `tile_overlap`; 0 = whole frame only. Costs tiles x rows + 1
    # inferences: 2 lifted recall of people of 8-32 px in 640-px keyframes 0.68 -> 0.85 (3.1x the time).
    tiles: int = Field(2, ge=0, le=8)
    tile_overlap: float = Field(0.2, ge=0, le=0.5)
    # A keyframe's inferences (whole frame and tiles) at once, up to one per core over all requests: the
    # same work, a lone keyframe answered sooner. False: one after another, on the request's thread.
    parallel_tiles: bool = True
    # With a closed-set kind (yolox, deimv2_*): the open-vocabulary detector for prompts naming no COCO class
    # (built from hf_model and device; needs the gpu extra). Empty: such prompts are answered 422 with the nearest known classes.
    open_vocabulary: Literal["", "grounding_dino", "owlv2"] = ""

    @model_validator(mode="after")
    def _int8_is_yolox(self) -> DetectorConfig:
        # Only YOLOX has int8 weights (backend_tools.quantize); a DEIMv2 kind would silently run fp32.
        if self.precision == "int8" and self.kind != "yolox":
            raise ValueError(f"precision int8 is for kind yolox only, not {self.kind}")
        return self


class CropConfig(ConfigSection):
    margin_px: int = Field(50, ge=0, le=500)  # the paper's 50 px context margin, clamped to the image


class VerifierConfig(ConfigSection):
    kind: VerifierKind = "local"
    timeout_s: float = Field(10.0, gt=0, le=300)  # one verification
    request_deadline_s: float = Field(20.0, gt=0, le=600)  # the whole request, detection included
    concurrency: int = Field(16, ge=1, le=512)  # verifications in flight, all vehicles together
    # The local verifier's pose-model interpreters: candidates are judged this many at once (0: one per
    # core; each holds the model, about 30 MB). 1: one after another, as before.
    local_instances: int = Field(0, ge=0, le=64)
    uncertain_policy: UncertainPolicy = "uncertain"  # what an unparseable or timed-out answer becomes


class VlmConfig(ConfigSection):
    base_url: str = "https://api.openai.com/v1"
    model: str = "gpt-4o-mini"
    api_key_env: str = "OPENAI_API_KEY"  # the key itself never sits in a file
    prompt_family: Literal["auto", "gpt", "llava", "paligemma"] = "auto"
    max_retries: int = Field(2, ge=0, le=10)
    backoff_s: float = Field(0.5, ge=0, le=30)
    max_tokens: int = Field(200, ge=1, le=4096)
    crop_max_side: int = Field(512, ge=32, le=4096)
    jpeg_quality: int = Field(90, ge=10, le=100)


StoreKind = Literal["sqlite", "redis"]


class SessionConfig(ConfigSection):
    detector_concurrency: int = Field(2, ge=1, le=64)  # requests in the detector at once
    max_queued_per_vehicle: int = Field(2, ge=1, le=100)  # beyond this a vehicle gets 429
    rejection_similarity: float = Field(0.85, gt=0, le=1)  # appearance correlation that counts as "same"
    rejection_radius_m: float = Field(150.0, gt=0, le=10_000)  # vehicle to rejected place, when both known
    mission_ttl_s: float = Field(6 * 3600.0, gt=0)  # forget a mission this long after its last request
    # Quotas per vehicle, answered with 429 and Retry-After.
    max_rejections_per_mission: int = Field(200, ge=1, le=10_000)
    max_missions_per_vehicle: int = Field(32, ge=1, le=10_000)  # live (not yet expired) missions
    rate_limit_requests: int = Field(120, ge=1, le=100_000)  # requests per vehicle per window
    rate_limit_window_s: float = Field(10.0, gt=0, le=3600)
    # Where the state lives: "sqlite" (one file, one server) or "redis" (shared by several replicas).
    store: StoreKind = "sqlite"
    # SQLite file; empty: $STATE_DIRECTORY/sessions.sqlite3 under systemd, else the user data folder.
    sqlite_path: str = ""
    redis_url: str = "redis://127.0.0.1:6379/0"


class SupervisorConfig(ConfigSection):
    # An optional tile layer under the page's map: a URL template with {z}, {x} and {y}, e.g. a tile server
    # on the rescue site's own network. Empty (the default): the map is drawn from the positions alone and
    # works with no internet at all.
    map_tiles: str = ""

    @field_validator("map_tiles")
    @classmethod
    def _template(cls, value: str) -> str:
        if value and (
            not value.startswith(("http://", "https://"))
            or not all(k in value for k in ("{z}", "{x}", "{y}"))
        ):
            raise ValueError("map_tiles must be an http(s) URL template with {z}, {x} and {y}")
        return value


class TakConfig(ConfigSection):
    # Where each confirmed find goes as a Cursor-on-Target event: "tcp://host:8087", "udp://host:6969"
    # (also multicast, e.g. udp://239.2.3.1:6969, what ATAK listens on), "tls://host:8089". Empty: off.
    url: str = ""
    callsign: str = "CloudTrack"  # the sender's name on the map (the find's own name says what it is)
    stale_s: float = Field(24 * 3600.0, gt=0, le=30 * 86400.0)  # how long the map shows the marker
    # TLS client certificate, key and CA (PEM files) for tls:// (TAK servers ask for a client certificate).
    tls_cert: str = ""
    tls_key: str = ""
    tls_ca: str = ""

    @field_validator("url")
    @classmethod
    def _scheme(cls, value: str) -> str:
        if value and not value.startswith(("tcp://", "udp://", "tls://")):
            raise ValueError("tak.url must start with tcp://, udp:// or tls:// (e.g. tcp://tak.local:8087)")
        return check_url(value) if value else value  # a port 0 or over 65535, a host that is no address


class FleetConfig(ConfigSection):
    # A vehicle of a mission that has sent no status for longer than this has dropped out of the search
    # (its link or companion lost): its unflown part is offered for a re-plan (GET /v1/missions/{m}/dropouts).
    # A companion reports every [backend] status_interval_s (1 s by default).
    dropout_s: float = Field(30.0, ge=1.0, le=3600.0)
    # A mission's merged map (GET /v1/missions/{m}/map, the supervisor page's fleet map) is merged again at
    # most once per this period, off the requests, and served as kept meanwhile (its `as_of` says since
    # when): one merge costs about 8 ms of CPU per vehicle (backend.merged_maps). 0: whenever read and changed.
    merge_period_s: float = Field(2.0, ge=0.0, le=60.0)


class BackendConfig(ConfigSection):
    server: ServerConfig = ServerConfig()
    auth: AuthConfig = AuthConfig()
    detector: DetectorConfig = DetectorConfig()
    crops: CropConfig = CropConfig()
    verifier: VerifierConfig = VerifierConfig()
    vlm: VlmConfig = VlmConfig()
    sessions: SessionConfig = SessionConfig()
    supervisor: SupervisorConfig = SupervisorConfig()
    tak: TakConfig = TakConfig()
    fleet: FleetConfig = FleetConfig()


def backend_environment(environ: Mapping[str, str]) -> dict[str, str]:
    """The variables meant for the back-end: CLOUDTRACK_BACKEND_<SECTION>__<KEY>.

    The companion's CLOUDTRACK_BACKEND__<KEY> (its [backend] section, note the double underscore) shares
    the prefix and is left out, so one environment can hold both processes' settings.
    """
    return {
        k: v
        for k, v in environ.items()
        if k.startswith(ENV_PREFIX) and not k[len(ENV_PREFIX) :].startswith("_")
    }


def load_backend_config(
    path: Path | None = None, assignments: Iterable[str] = (), environ: Mapping[str, str] | None = None
) -> BackendConfig:
    """Defaults, then FILE, then the environment, then --set flags; ConfigError on anything not allowed."""
    full = os.environ if environ is None else environ
    return load_config(
        BackendConfig,
        path,
        env_prefix=ENV_PREFIX,
        environ=backend_environment(full),
        assignments=assignments,
        default_files=default_config_files(CONFIG_FILE_NAME, full),
    )
