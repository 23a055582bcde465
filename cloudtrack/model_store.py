"""The weight files CloudTrack knows, where to find them, and how to fetch and verify them.

Lookup order for the model directory: an explicit `--model-dir` flag, then `CLOUDTRACK_MODEL_DIR`, then
the user cache (`$XDG_CACHE_HOME/cloudtrack/models`, default `~/.cache/cloudtrack/models`).
"""

from __future__ import annotations

import difflib
import hashlib
import os
import sys
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from urllib.parse import urlsplit

from cloudtrack.connection_errors import connection_cause

MODEL_DIR_ENV = "CLOUDTRACK_MODEL_DIR"
# The help of the one --model-dir flag every command that loads weights takes.
MODEL_DIR_HELP = "folder of weight files (default: $CLOUDTRACK_MODEL_DIR, then ~/.cache/cloudtrack/models)"


@dataclass(frozen=True)
class ModelFile:
    """One file of a model, relative to the model directory. sha256/size are None for user-supplied files."""

    relpath: str
    sha256: str | None
    size: int | None
    url: str | None


@dataclass(frozen=True)
class ModelSpec:
    name: str
    description: str
    licence: str
    files: tuple[ModelFile, ...]
    user_supplied: bool = False


REGISTRY: Mapping[str, ModelSpec] = {
    spec.name: spec
    for spec in (
        ModelSpec(
            "nano",
            "NanoTrack v2 (backbone + head) for cv2.TrackerNano",
            "Apache-2.0",
            (
                ModelFile(
                    "nanotrack_v2/nanotrack_backbone_sim.onnx",
                    "530bdd0cd00f19afab79a863e71ba71e3312395a5dc9151af675082bdaaa2fc4",
                    1056849,
                    "https://raw.githubusercontent.com/HonglinChu/SiamTrackers/master/NanoTrack/models/nanotrackv2/nanotrack_backbone_sim.onnx",
                ),
                ModelFile(
                    "nanotrack_v2/nanotrack_head_sim.onnx",
                    "0d8c0637be849f092cc7236cae02e55c8b9455ebe37ba50601d6115db4247cd9",
                    726198,
                    "https://raw.githubusercontent.com/HonglinChu/SiamTrackers/master/NanoTrack/models/nanotrackv2/nanotrack_head_sim.onnx",
                ),
            ),
        ),
        ModelSpec(
            "vit",
            "VitTrack 2023sep for cv2.TrackerVit",
            "Apache-2.0",
            (
                ModelFile(
                    "vittrack/object_tracking_vittrack_2023sep.onnx",
                    "2990f0b7cd44d92afa48cd97db6de7be113fc1d9594fddb74e2725c10478e91d",
                    714726,
                    "https://github.com/opencv/opencv_zoo/raw/main/models/object_tracking_vittrack/object_tracking_vittrack_2023sep.onnx",
                ),
            ),
        ),
        ModelSpec(
            "yolox",
            "YOLOX-nano, COCO-80, 416x416 input (the back-end's offline detector)",
            "Apache-2.0",
            (
                ModelFile(
                    "yolox_nano/yolox_nano.onnx",
                    "c789161ed43c8269fcd4e67c67eeeb4e80c622da2eb296a20bc6007bd18a0b7d",
                    3659407,
                    "https://github.com/Megvii-BaseDetection/YOLOX/releases/download/0.1.1rc0/yolox_nano.onnx",
                ),
            ),
        ),
        # DEIMv2 (DETR-style, COCO-80), an alternative superset detector (`[detector] kind`); the ONNX
        # exports MODELS.md names, pinned to their commit.
        ModelSpec(
            "deimv2_atto",
            'DEIMv2-Atto, COCO-80, 320x320 input (`[detector] kind = "deimv2_atto"`)',
            "Apache-2.0",
            (
                ModelFile(
                    "deimv2/deimv2_hgnetv2_atto_coco.onnx",
                    "b114aa6610ac7c2bd9b3186ffb001afa872430db957407ef2473f7148d00646e",
                    2248408,
                    "https://raw.githubusercontent.com/Kazuhito00/DEIMv2-ONNX-Sample/f88d4382/model/deimv2_hgnetv2_atto_coco.onnx",
                ),
            ),
        ),
        ModelSpec(
            "deimv2_femto",
            'DEIMv2-Femto, COCO-80, 416x416 input (`[detector] kind = "deimv2_femto"`)',
            "Apache-2.0",
            (
                ModelFile(
                    "deimv2/deimv2_hgnetv2_femto_coco.onnx",
                    "c6ad358f750132b891165e034c2ba507abefc5ebe1c1d2732a0acbcacc47e52c",
                    4116144,
                    "https://raw.githubusercontent.com/Kazuhito00/DEIMv2-ONNX-Sample/f88d4382/model/deimv2_hgnetv2_femto_coco.onnx",
                ),
            ),
        ),
        ModelSpec(
            "dasiamrpn",
            "DaSiamRPN (model + two kernels) for cv2.TrackerDaSiamRPN; about 160 MB",
            "see upstream (foolwood/DaSiamRPN)",
            (
                ModelFile(
                    "dasiamrpn/dasiamrpn_model.onnx",
                    None,
                    None,
                    "https://www.dropbox.com/s/rr1lk9355vzolqv/dasiamrpn_model.onnx?dl=1",
                ),
                ModelFile(
                    "dasiamrpn/dasiamrpn_kernel_r1.onnx",
                    None,
                    None,
                    "https://www.dropbox.com/s/999cqx5zrfi7w4p/dasiamrpn_kernel_r1.onnx?dl=1",
                ),
                ModelFile(
                    "dasiamrpn/dasiamrpn_kernel_cls1.onnx",
                    None,
                    None,
                    "https://www.dropbox.com/s/qvmtszx5h339a0w/dasiamrpn_kernel_cls1.onnx?dl=1",
                ),
            ),
            user_supplied=True,
        ),
        ModelSpec(
            "goturn",
            "GOTURN (prototxt + caffemodel) for cv2.TrackerGOTURN on OpenCV 4.x; about 370 MB",
            "see upstream (davheld/GOTURN)",
            (
                ModelFile("goturn/goturn.prototxt", None, None, None),
                ModelFile("goturn/goturn.caffemodel", None, None, None),
            ),
            user_supplied=True,
        ),
    )
}


class FileStatus(str, Enum):
    VERIFIED = "present+verified"
    UNVERIFIED = "present (user-supplied, no checksum)"
    MISSING = "missing"
    CORRUPT = "corrupt"


class ModelError(Exception):
    """A model that cannot be used; the message names the file and the command that fixes it."""


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cloudtrack" / "models"


def resolve_model_dir(explicit: str | Path | None = None, environ: Mapping[str, str] | None = None) -> Path:
    """--model-dir, else $CLOUDTRACK_MODEL_DIR, else the user cache directory."""
    env = os.environ if environ is None else environ
    if explicit:
        return Path(explicit).expanduser()
    if env.get(MODEL_DIR_ENV):
        return Path(env[MODEL_DIR_ENV]).expanduser()
    return default_cache_dir()


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def file_status(model_dir: Path, mf: ModelFile) -> FileStatus:
    path = model_dir / mf.relpath
    if not path.is_file():
        return FileStatus.MISSING
    if mf.sha256 is None:
        return FileStatus.UNVERIFIED
    if mf.size is not None and path.stat().st_size != mf.size:
        return FileStatus.CORRUPT
    return FileStatus.VERIFIED if sha256_of(path) == mf.sha256 else FileStatus.CORRUPT


def _fix_hint(spec: ModelSpec, model_dir: Path) -> str:
    if spec.user_supplied:
        urls = ", ".join(f.url for f in spec.files if f.url) or "the upstream project"
        return (
            f"place the files under {model_dir} (sources: {urls}), "
            f"or run `cloudtrack-companion models download {spec.name} --model-dir {model_dir}`"
            if any(f.url for f in spec.files)
            else f"place the files under {model_dir} (from {spec.licence})"
        )
    return f"run `cloudtrack-companion models download {spec.name} --model-dir {model_dir}`"


def _missing_folder(model_dir: Path) -> str:
    """A folder that does not exist is most often a typo: name the folder, never offer to download into it."""
    message = (
        f"model folder {model_dir} does not exist: check --model-dir and ${MODEL_DIR_ENV} "
        f"(default {default_cache_dir()})"
    )
    parent = model_dir.parent
    if parent.is_dir():
        siblings = [p.name for p in parent.iterdir() if p.is_dir()]
        close = difflib.get_close_matches(model_dir.name, siblings, n=1, cutoff=0.6)
        if close:
            return f"{message}; did you mean {parent / close[0]}?"
    elif parent.parent.is_dir():
        # A typo one level up (../shard/models for ../shared/models).
        uncles = [p.name for p in parent.parent.iterdir() if (p / model_dir.name).is_dir()]
        close = difflib.get_close_matches(parent.name, uncles, n=1, cutoff=0.6)
        if close:
            return f"{message}; did you mean {parent.parent / close[0] / model_dir.name}?"
    return message


def require(name: str, model_dir: Path) -> dict[str, Path]:
    """Paths of a model's files, checked; raises ModelError naming the bad file and the fixing command.

    Checksums are verified here (a few ms for these files) so a corrupt download never reaches OpenCV,
    whose own error for a bad ONNX file names neither the file nor the cure.
    """
    if name not in REGISTRY:
        raise ModelError(f"unknown model {name!r}; known: {', '.join(REGISTRY)}")
    spec = REGISTRY[name]
    if not model_dir.is_dir() and model_dir != default_cache_dir():  # the cache is made by `models download`
        raise ModelError(_missing_folder(model_dir))
    paths: dict[str, Path] = {}
    for mf in spec.files:
        status = file_status(model_dir, mf)
        path = model_dir / mf.relpath
        if status is FileStatus.MISSING:
            raise ModelError(f"model {name!r}: file {path} is missing; {_fix_hint(spec, model_dir)}")
        if status is FileStatus.CORRUPT:
            raise ModelError(
                f"model {name!r}: file {path} is corrupt (sha256 does not match); {_fix_hint(spec, model_dir)}"
            )
        paths[Path(mf.relpath).name] = path
    return paths


def download(
    name: str,
    model_dir: Path,
    fetch: Callable[[str, Path], None] | None = None,
) -> list[Path]:
    """Fetch every file of a model from its upstream URL, verify sha256 and move it into place atomically.

    `fetch(url, destination)` writes the URL's bytes to destination; the default streams with requests.
    A file that is already present and verified is not fetched again.
    """
    if name not in REGISTRY:
        raise ModelError(f"unknown model {name!r}; known: {', '.join(REGISTRY)}")
    spec = REGISTRY[name]
    fetch = fetch or _http_fetch
    written: list[Path] = []
    for mf in spec.files:
        target = model_dir / mf.relpath
        if file_status(model_dir, mf) in (FileStatus.VERIFIED, FileStatus.UNVERIFIED):
            continue
        if mf.url is None:
            raise ModelError(f"model {name!r}: {target} has no download URL; {_fix_hint(spec, model_dir)}")
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=target.name + ".", suffix=".part", dir=target.parent)
        os.close(fd)
        tmp = Path(tmp_name)
        try:
            fetch(mf.url, tmp)
            if mf.sha256 is not None and sha256_of(tmp) != mf.sha256:
                raise ModelError(
                    f"model {name!r}: download of {mf.url} does not match sha256 {mf.sha256}; not installed"
                )
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        written.append(target)
    return written


def _http_fetch(url: str, destination: Path) -> None:
    """Stream URL to destination with a progress bar on stderr; network failures become one clear ModelError."""
    import requests
    from tqdm import tqdm

    host = urlsplit(url).hostname or url
    try:
        with requests.get(url, stream=True, timeout=(10, 60)) as response:
            response.raise_for_status()
            total = int(response.headers.get("Content-Length") or 0) or None
            with (
                open(destination, "wb") as f,
                tqdm(
                    total=total,
                    unit="B",
                    unit_scale=True,
                    unit_divisor=1024,
                    desc=Path(urlsplit(url).path).name,
                    file=sys.stderr,
                ) as bar,
            ):
                for chunk in response.iter_content(chunk_size=1 << 16):
                    f.write(chunk)
                    bar.update(len(chunk))
    except requests.ConnectionError as exc:
        raise ModelError(
            f"cannot reach {host} to download {url} ({connection_cause(exc)}): this machine looks offline. Connect it "
            f"to the internet, or use weights you already have: --model-dir DIR or {MODEL_DIR_ENV}=DIR "
            "(e.g. ../shared/models), or copy the files into the model directory"
        ) from None
    except requests.Timeout:
        raise ModelError(f"{host} did not answer in time while downloading {url}; try again later") from None
    except requests.HTTPError as exc:
        raise ModelError(
            f"{url} answered {exc.response.status_code if exc.response is not None else '?'}; "
            "the upstream file may have moved"
        ) from None
