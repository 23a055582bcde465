"""The labelled person-crop set the local verifier is calibrated and scored on.

Each crop is a box in a frame of a shared sequence (never a copy of the pixels) with what a person saw
when looking at it: the upper and lower garment colours and the posture. The set is built in two steps:
`propose` lists the target (ground truth) and every other person YOLOX-nano finds on sampled frames, and
`contact_sheet` draws numbered grids of them to label by eye.

    python -m backend_tools.crop_set propose --sequences ../shared/data/sequences --models ../shared/models \
        --out proposals.json
    python -m backend_tools.crop_set sheets proposals.json --sequences ../shared/data/sequences --out sheets/

Objects that are not people (tests/data/object_crops.json: cars, boats, the bag, labelled with the colours of
their paint or hull) the same way, from the companion's 640 px keyframes:

    python -m backend_tools.crop_set propose-objects --sequences ../shared/data/sequences \
        --models ../shared/models --step 25 --out objects.json
    python -m backend_tools.crop_set sheets objects.json --objects --sequences ../shared/data/sequences --out sheets/
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

COLOUR_NAMES = (
    "black",
    "white",
    "gray",
    "red",
    "orange",
    "yellow",
    "green",
    "blue",
    "purple",
    "pink",
    "brown",
)
POSTURES = ("standing", "sitting", "lying")


@dataclass(frozen=True)
class LabelledCrop:
    sequence: str
    frame: int  # 1-based, as in frames/000001.jpg
    box: tuple[int, int, int, int]  # x, y, w, h in the frame's pixels
    source: str  # "target" (ground truth) or "yolox"
    upper: tuple[str, ...] = ()  # garment colours seen; empty: not labelled / cannot be seen
    lower: tuple[str, ...] = ()
    posture: str = ""  # one of POSTURES; "" for a box that is not one whole person (see note)
    note: str = ""

    @property
    def key(self) -> str:
        return f"{self.sequence}:{self.frame}:{','.join(map(str, self.box))}"


def load_crops(path: Path) -> list[LabelledCrop]:
    rows = json.loads(path.read_text())
    return [
        LabelledCrop(
            r["sequence"],
            r["frame"],
            tuple(r["box"]),
            r["source"],
            tuple(r.get("upper", ())),
            tuple(r.get("lower", ())),
            r.get("posture", ""),
            r.get("note", ""),
        )
        for r in rows
    ]


def save_crops(crops: list[LabelledCrop], path: Path) -> None:
    rows = [{k: v for k, v in asdict(c).items() if v != ""} for c in crops]
    path.write_text("[\n" + ",\n".join(json.dumps(r) for r in rows) + "\n]\n")


def frame_path(sequences_dir: Path, crop: LabelledCrop | ObjectCrop) -> Path:
    return sequences_dir / crop.sequence / "frames" / f"{crop.frame:06d}.jpg"


def read_frame(sequences_dir: Path, crop: LabelledCrop | ObjectCrop) -> np.ndarray:
    image = cv2.imread(str(frame_path(sequences_dir, crop)))
    if image is None:
        raise FileNotFoundError(frame_path(sequences_dir, crop))
    return image


def _iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    ix = max(0.0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    inter = ix * iy
    return inter / max(a[2] * a[3] + b[2] * b[3] - inter, 1e-9)


def propose(sequences_dir: Path, models_dir: Path, step: int, min_height: int = 20) -> list[LabelledCrop]:
    """Target and YOLOX person boxes every `step` frames of each person sequence (unlabelled)."""
    from backend.detectors.yolox import YoloxDetector

    detector = YoloxDetector(models_dir / "yolox_nano" / "yolox_nano.onnx", threads=1)
    crops: list[LabelledCrop] = []
    for seq in sorted(p for p in sequences_dir.iterdir() if (p / "groundtruth.txt").exists()):
        gt = [
            tuple(float(v) for v in line.split(",")) for line in (seq / "groundtruth.txt").read_text().split()
        ]
        frames = sorted((seq / "frames").glob("*.jpg"))
        for index in range(1, len(frames) + 1, step):
            image = np.asarray(cv2.imread(str(frames[index - 1])))
            target = gt[index - 1]
            found = [d.box for d in detector.detect(image, ["person"])]
            boxes: list[tuple[float, ...]] = [target] if target[2] > 1 and target[3] > 1 else []
            is_person_target = any(_iou(target, (b.x, b.y, b.w, b.h)) >= 0.3 for b in found)
            if not is_person_target:
                boxes = []  # the target is no person (the bag) or YOLOX cannot see one here
            others: list[tuple[float, ...]] = [
                (b.x, b.y, b.w, b.h) for b in found if _iou(target, (b.x, b.y, b.w, b.h)) < 0.3
            ]
            for n, box in enumerate(boxes + others):
                if box[3] < min_height:
                    continue
                x, y, w, h = (int(round(v)) for v in box)
                role = "target" if (boxes and n == 0) else "yolox"
                crops.append(LabelledCrop(seq.name, index, (x, y, w, h), role))
    return crops


# Sequences whose target is not a person, and the class their objects are proposed as (the description's).
OBJECT_SEQUENCES = {
    "uav123_boat5": "boat",
    "uav123_wakeboard7": "boat",
    "uav123_bike1": "car",
    "uavdt_S1606": "car",
    "uavdt_S1301": "car",
    "uavdt_S0601": "car",
    "vot2015_bag": "bag",
}


@dataclass(frozen=True)
class ObjectCrop:
    """An object that is not a person, with the colours a person saw on it (its paint, its hull)."""

    sequence: str
    frame: int
    box: tuple[int, int, int, int]  # x, y, w, h in the frame's pixels
    source: str  # "target" or "yolox"
    kind: str  # the class it was proposed as: "car", "boat", "bag"
    colours: tuple[str, ...] = ()  # empty: not labelled / cannot be seen
    note: str = ""

    @property
    def key(self) -> str:
        return f"{self.sequence}:{self.frame}:{','.join(map(str, self.box))}"


def load_objects(path: Path) -> list[ObjectCrop]:
    return [
        ObjectCrop(
            r["sequence"], r["frame"], tuple(r["box"]), r["source"], r["kind"], tuple(r.get("colours", ())),
            r.get("note", ""),
        )
        for r in json.loads(path.read_text())
    ]  # fmt: skip


def save_objects(crops: list[ObjectCrop], path: Path) -> None:
    rows = [{k: v for k, v in asdict(c).items() if v not in ("", ())} for c in crops]
    path.write_text("[\n" + ",\n".join(json.dumps(r) for r in rows) + "\n]\n")


def propose_objects(sequences_dir: Path, models_dir: Path, step: int, min_side: int = 8) -> list[ObjectCrop]:
    """The target and every box of its class the back-end's tiled YOLOX finds in the companion's 640 px
    keyframe, every `step` frames of each object sequence (boxes in the frame's own pixels; unlabelled)."""
    from backend.detectors.tiling import TiledDetector
    from backend.detectors.yolox import YoloxDetector
    from cloudtrack.api_client import encode_keyframe

    yolox = YoloxDetector(models_dir / "yolox_nano" / "yolox_nano.onnx", threads=1)
    detector = TiledDetector(yolox, 2, min_side=yolox.input_size)
    crops: list[ObjectCrop] = []
    for name, kind in OBJECT_SEQUENCES.items():
        seq = sequences_dir / name
        if not (seq / "groundtruth.txt").exists():
            continue
        gt = [
            tuple(float(v) for v in line.split(",")) for line in (seq / "groundtruth.txt").read_text().split()
        ]
        frames = sorted((seq / "frames").glob("*.jpg"))
        for index in range(1, len(frames) + 1, step):
            image = np.asarray(cv2.imread(str(frames[index - 1])))
            jpeg, scale = encode_keyframe(image, 640, 80)
            sent = np.asarray(cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR))
            found = [d.box.scaled(1 / scale, 1 / scale) for d in detector.detect(sent, [kind])]
            target = gt[index - 1]
            boxes = [(target, "target")] if kind != "car" or name != "uav123_bike1" else []
            boxes += [
                ((b.x, b.y, b.w, b.h), "yolox") for b in found if _iou(target, (b.x, b.y, b.w, b.h)) < 0.3
            ]
            for box, source in boxes:
                if min(box[2], box[3]) * scale < min_side:
                    continue
                x, y, w, h = (int(round(v)) for v in box)
                crops.append(ObjectCrop(name, index, (x, y, w, h), source, kind))
    return crops


def contact_sheet(
    crops: Sequence[LabelledCrop | ObjectCrop],
    sequences_dir: Path,
    first_number: int,
    cell: int = 160,
    columns: int = 8,
) -> np.ndarray:
    """A grid of numbered crops (the box outlined, with some context), numbers from `first_number`."""
    rows = (len(crops) + columns - 1) // columns
    sheet = np.full((rows * (cell + 18), columns * cell, 3), 255, np.uint8)
    for i, crop in enumerate(crops):
        image = read_frame(sequences_dir, crop)
        x, y, w, h = crop.box
        side = int(max(w, h) * 1.3) + 4
        cx, cy = x + w / 2, y + h / 2
        scale = cell / side
        m = np.array([[scale, 0, cell / 2 - cx * scale], [0, scale, cell / 2 - cy * scale]], np.float32)
        view = cv2.warpAffine(image, m, (cell, cell), flags=cv2.INTER_CUBIC, borderValue=(255, 255, 255))
        p1 = (int((x - cx) * scale + cell / 2) - 1, int((y - cy) * scale + cell / 2) - 1)
        p2 = (int((x + w - cx) * scale + cell / 2) + 1, int((y + h - cy) * scale + cell / 2) + 1)
        cv2.rectangle(view, p1, p2, (0, 255, 255), 1)
        r, c = divmod(i, columns)
        sheet[r * (cell + 18) + 18 : r * (cell + 18) + 18 + cell, c * cell : (c + 1) * cell] = view
        cv2.putText(
            sheet,
            f"{first_number + i} {crop.sequence[:10]} {h}px",
            (c * cell + 2, r * (cell + 18) + 13),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (0, 0, 0),
            1,
        )
    return sheet


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m backend_tools.crop_set",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    prop = sub.add_parser("propose", help="list target and YOLOX person boxes (unlabelled) as JSON")
    prop.add_argument(
        "--sequences", type=Path, required=True, help="folder of sequences (frames/, groundtruth.txt)"
    )
    prop.add_argument("--models", type=Path, required=True, help="folder with yolox_nano/yolox_nano.onnx")
    prop.add_argument("--step", type=int, default=10, help="every STEP-th frame (default 10)")
    prop.add_argument("--out", type=Path, required=True)
    objects = sub.add_parser(
        "propose-objects",
        help="list the target and the back-end's tiled YOLOX boxes of its class in 640 px keyframes of the "
        "sequences whose target is not a person (unlabelled) as JSON",
    )
    objects.add_argument("--sequences", type=Path, required=True)
    objects.add_argument("--models", type=Path, required=True)
    objects.add_argument("--step", type=int, default=25, help="every STEP-th frame (default 25)")
    objects.add_argument("--out", type=Path, required=True)
    sheets = sub.add_parser("sheets", help="numbered contact sheets (PNG) of a crop list, to label by eye")
    sheets.add_argument("crops", type=Path)
    sheets.add_argument("--sequences", type=Path, required=True)
    sheets.add_argument("--out", type=Path, required=True, help="folder for sheet_NN.png")
    sheets.add_argument("--per-sheet", type=int, default=40, help="crops per sheet (default 40)")
    sheets.add_argument("--objects", action="store_true", help="the list is objects (propose-objects)")
    args = parser.parse_args(argv)
    if args.command == "propose":
        people = propose(args.sequences, args.models, args.step)
        save_crops(people, args.out)
        print(f"{len(people)} crops -> {args.out}")
        return 0
    if args.command == "propose-objects":
        found = propose_objects(args.sequences, args.models, args.step)
        save_objects(found, args.out)
        print(f"{len(found)} objects -> {args.out}")
        return 0
    crops: Sequence[LabelledCrop | ObjectCrop] = (
        load_objects(args.crops) if args.objects else load_crops(args.crops)
    )
    args.out.mkdir(parents=True, exist_ok=True)
    for n, start in enumerate(range(0, len(crops), args.per_sheet)):
        path = args.out / f"sheet_{n:02d}.png"
        cv2.imwrite(str(path), contact_sheet(crops[start : start + args.per_sheet], args.sequences, start))
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
