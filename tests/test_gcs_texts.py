"""docs/gcs-protocol.md says what the tools say: its table of status lines is compared with every STATUSTEXT
the code can send (read from the source: the string or f-string given to `GcsMessage`, `send_status`,
`status` and the operator's notices), both ways, and every example line on that page must be one of the
table's lines with real values. Select: -k texts.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "gcs-protocol.md"
SOURCES = [*sorted((REPO / "behaviors").glob("*.py")), *sorted((REPO / "companion").rglob("*.py")),
           REPO / "cloudtrack" / "gcs_protocol.py"]  # fmt: skip
SENDERS = {"GcsMessage", "send_status", "status"}
# Functions whose strings are reasons the operator reads as they are (companion/operator_notices.py etc.).
# (Waiting for the autopilot is no STATUSTEXT: without it there is no link to the GCS.)
REASON_PRODUCERS = {"backend_problem", "verdict_for", "auth_reason"}
STATES = "IDLE|SEARCHING|ACQUIRING|FOLLOWING|AWAITING_SUPERVISOR|CONFIRMED|REJECTED|LOST|ABORTED"
PLACEHOLDERS = {
    "<id>": r"\d{1,3}",
    "<item>": r"\d+",
    "<STATE>": f"(?:{STATES})",
    "<STATUS>": "(?:AWAITING|REVERIFIED)",
    "<COMMAND>": "(?:START|ABORT|CONFIRM|REJECT|STATUS|TRACK-RECTANGLE|TRACK-POINT|STOP-TRACKING)",
    "<candidate id>": r"[A-Za-z0-9_.-]{1,64}",
    "<lat>": r"-?\d{1,2}\.\d{6}",
    "<lon>": r"-?\d{1,3}\.\d{6}",
    "<sigma>": r"\d+\.\d",
    "<status>": r"\d{3}",
}


def documented() -> list[str]:
    text = DOC.read_text()
    table = text.split("<!-- statustext: begin -->")[1].split("<!-- statustext: end -->")[0]
    return re.findall(r"^\| `([^`]+)` \|", table, flags=re.MULTILINE)


def _template(node: ast.expr) -> str | None:
    """A string literal as it is; an f-string with each value as `<>`; None for anything else."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        return "".join(v.value if isinstance(v, ast.Constant) else "<>" for v in node.values)
    if isinstance(node, ast.Subscript):  # f"..."[:50]
        return _template(node.value)
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "strip":
        return _template(node.func.value)
    return None


def code_texts() -> dict[str, str]:
    """Every status line template in the code, with where it is."""
    found: dict[str, str] = {}
    for path in SOURCES:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and node.args:
                name = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", "")
                if name in SENDERS:
                    template = _template(node.args[0])
                    if template is not None:
                        found[template] = f"{path.relative_to(REPO)}:{node.lineno}"
            if isinstance(node, ast.FunctionDef) and node.name in REASON_PRODUCERS:
                for inner in ast.walk(node):
                    if isinstance(inner, ast.JoinedStr):
                        template = _template(inner)
                        if template and template.strip("<> ") and not template.startswith("back-end "):
                            found[template] = f"{path.relative_to(REPO)}:{inner.lineno}"
    return found


def _loose(template: str) -> re.Pattern[str]:
    """A code template as a pattern: each `<>` any text (also none)."""
    return re.compile("".join(".*" if p == "<>" else re.escape(p) for p in re.split(r"(<>)", template)), re.S)


def _strict(documented_line: str) -> re.Pattern[str]:
    """A documented line as a pattern for real lines: known placeholders as their values, others any text."""
    parts = re.split(r"(<[^<>]+>)", documented_line)
    return re.compile(
        "".join(PLACEHOLDERS.get(p, ".+") if p.startswith("<") else re.escape(p) for p in parts)
    )


def test_texts_every_status_line_of_the_code_is_documented() -> None:
    lines = documented()
    missing = {
        template: where
        for template, where in code_texts().items()
        if template.strip() and not any(_loose(template).fullmatch(line) for line in lines)
    }
    assert not missing, f"status lines the docs' table lacks: {missing}"


def test_texts_every_documented_status_line_is_the_codes() -> None:
    templates = [t for t in code_texts() if t.strip("<> ")]
    stale = [line for line in documented() if not any(_loose(t).fullmatch(line) for t in templates)]
    assert not stale, f"documented status lines no code sends: {stale}"


def test_texts_every_example_on_the_page_is_a_documented_line() -> None:
    page = DOC.read_text()
    examples = re.findall(r'STATUSTEXT "([^"]+)"', page)
    bullet = page.split("- **STATUSTEXT**")[1].split("\n- ")[0]
    examples += re.findall(r"`([^`<]+)`", bullet)
    examples = [" ".join(e.split()) for e in examples if not e.startswith(("cloudtrack", "id", "chunk"))]
    assert len(examples) >= 5, examples
    patterns = [_strict(line) for line in documented()]
    wrong = [e for e in examples if not any(p.fullmatch(e) for p in patterns)]
    assert not wrong, f"examples on the page that are no line the companion sends: {wrong}"
