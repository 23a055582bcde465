from __future__ import annotations

import functools
import http.server
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from cloudtrack.model_store import (
    REGISTRY,
    FileStatus,
    ModelError,
    download,
    file_status,
    require,
    resolve_model_dir,
)


def test_shared_models_verify(models_dir: Path) -> None:
    for name in ("nano", "vit", "yolox", "deimv2_atto", "deimv2_femto"):
        for mf in REGISTRY[name].files:
            assert file_status(models_dir, mf) is FileStatus.VERIFIED, mf.relpath
        assert all(p.is_file() for p in require(name, models_dir).values())


def test_lookup_order(tmp_path: Path) -> None:
    assert resolve_model_dir("/flag", {"CLOUDTRACK_MODEL_DIR": "/env"}) == Path("/flag")
    assert resolve_model_dir(None, {"CLOUDTRACK_MODEL_DIR": "/env"}) == Path("/env")
    cache = resolve_model_dir(None, {})
    assert cache.parts[-2:] == ("cloudtrack", "models")


def test_missing_and_user_supplied_errors_name_file_and_fix(tmp_path: Path) -> None:
    with pytest.raises(ModelError) as info:
        require("nano", tmp_path)
    assert "nanotrack_backbone_sim.onnx" in str(info.value)
    assert "cloudtrack-companion models download nano" in str(info.value)
    with pytest.raises(ModelError, match="dasiamrpn_model.onnx"):
        require("dasiamrpn", tmp_path)


@pytest.mark.parametrize(
    ("typo", "meant"),
    [("shard/models", "shared/models"), ("shared/modles", "shared/models"), ("elsewhere/x", None)],
)
def test_a_model_folder_that_does_not_exist_is_named_never_offered_for_download(
    tmp_path: Path, typo: str, meant: str | None
) -> None:
    (tmp_path / "shared" / "models").mkdir(parents=True)
    with pytest.raises(ModelError) as info:
        require("nano", tmp_path / typo)
    message = str(info.value)
    assert f"model folder {tmp_path / typo} does not exist" in message and "--model-dir" in message
    assert "download" not in message  # never into the misspelt folder
    assert (f"did you mean {tmp_path / meant}?" in message) if meant else "did you mean" not in message


def _corrupt_copy(models_dir: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "models"
    shutil.copytree(models_dir, copy)
    target = copy / "vittrack" / "object_tracking_vittrack_2023sep.onnx"
    target.chmod(0o644)
    data = bytearray(target.read_bytes())
    data[1000] ^= 0xFF
    target.write_bytes(bytes(data))
    return copy


def test_one_flipped_byte_is_corrupt(models_dir: Path, tmp_path: Path) -> None:
    copy = _corrupt_copy(models_dir, tmp_path)
    with pytest.raises(ModelError, match="corrupt"):
        require("vit", copy)
    assert require("nano", copy)


def test_models_list_cli(models_dir: Path, tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "companion.cli", "models", "list", "--model-dir"]
    ok = subprocess.run([*cmd, str(models_dir)], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    for name in ("nano", "vit", "yolox", "deimv2_atto", "deimv2_femto"):
        assert any(
            line.split()[:3] == [name, "downloadable", "present+verified"]
            for line in ok.stdout.splitlines()
            if line.strip()
        )
    for name in ("dasiamrpn", "goturn"):
        assert any(line.split()[:2] == [name, "user-supplied"] for line in ok.stdout.splitlines()), name
    bad = subprocess.run([*cmd, str(_corrupt_copy(models_dir, tmp_path))], capture_output=True, text=True)
    assert bad.returncode != 0
    corrupt_lines = [line for line in bad.stdout.splitlines() if "corrupt" in line]
    assert len(corrupt_lines) == 1 and "object_tracking_vittrack_2023sep.onnx" in corrupt_lines[0]


def test_download_verifies_and_writes_atomically(models_dir: Path, tmp_path: Path) -> None:
    source = {mf.url: models_dir / mf.relpath for mf in REGISTRY["nano"].files}

    def fetch(url: str, dest: Path) -> None:
        shutil.copyfile(source[url], dest)

    written = download("nano", tmp_path, fetch=fetch)
    assert len(written) == 2 and require("nano", tmp_path)
    assert download("nano", tmp_path, fetch=fetch) == []  # already verified: nothing fetched


def test_download_with_wrong_bytes_installs_nothing(tmp_path: Path) -> None:
    def fetch(url: str, dest: Path) -> None:
        dest.write_bytes(b"not a model")

    with pytest.raises(ModelError, match="does not match sha256"):
        download("vit", tmp_path, fetch=fetch)
    assert not any(tmp_path.rglob("*.onnx")) and not any(tmp_path.rglob("*.part"))


class _FileServer:
    """A real HTTP server on loopback serving one folder."""

    def __init__(self, folder: Path) -> None:
        handler = functools.partial(_QuietHandler, directory=str(folder))
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: object) -> None:
        pass


def test_models_download_shows_progress_over_http(
    models_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from cloudtrack.model_store import _http_fetch

    server = _FileServer(models_dir / "yolox_nano")
    try:
        _http_fetch(f"{server.url}/yolox_nano.onnx", tmp_path / "yolox_nano.onnx")
    finally:
        server.close()
    assert (tmp_path / "yolox_nano.onnx").read_bytes() == (
        models_dir / "yolox_nano" / "yolox_nano.onnx"
    ).read_bytes()
    err = capsys.readouterr().err
    assert "yolox_nano.onnx" in err and "100%" in err  # tqdm's bar, sized from Content-Length


def test_models_download_offline_says_so_in_a_sentence(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from dataclasses import replace

    from companion.cli import main

    # .invalid never resolves (RFC 2606): the same failure a machine without network gives.
    spec = REGISTRY["vit"]
    offline = replace(
        spec, files=tuple(replace(mf, url="https://weights.cloudtrack.invalid/vit.onnx") for mf in spec.files)
    )
    monkeypatch.setitem(REGISTRY, "vit", offline)  # type: ignore[arg-type]
    assert main(["models", "download", "vit", "--model-dir", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert (
        "cannot reach weights.cloudtrack.invalid" in err
        and "offline" in err
        and "name resolution failed" in err
    )
    assert "NameResolutionError" not in err and "Traceback" not in err
    assert not any(tmp_path.rglob("*.part"))
