"""Issue 44 items 1, 2 and 4: what a vehicle or an operator wrote reaches the rescuers' documents as text.

The Cursor-on-Target event (back-end and `cloudtrack-gcs watch`) and the KML download of every payload below
parse with a strict XML parser (lxml, and the standard library's expat), hold none of the characters XML
1.0 forbids, and carry the words as text: no element, no HTML balloon, no link the vehicle wrote. The API
strips control characters from the text fields of statuses and finds on the way in. Select: -k hostile.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import pytest
import requests
from lxml import etree

from backend.app import create_app
from backend.serving import BackgroundServer
from cloudtrack.cursor_on_target import FindReport, find_event
from tests.backend_fixtures import TOKENS, backend_config

# What XML 1.0 forbids, as the issue found it passing through (and the rest of its class).
FORBIDDEN = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")
INJECTION = (
    "<![CDATA[<img src=x onerror=alert(1)><a href=http://evil.example/>x</a>]]>"
    "<name>FAKE</name><Point><coordinates>0,0</coordinates></Point>"
)
PAYLOADS = {
    "ampersand": "a man in a black & white shirt",
    "less-than": "a man < 2 m tall",
    "cdata-end": "a man ]]> in red",
    "controls": "a man\x00\x01\x0b\x0c in red",
    "noncharacters": "a man \ufffe\uffff in red",
    "lone-surrogate": "a man \ud800 in red",
    "injection": INJECTION,
}


def _strict(data: bytes) -> etree._Element:
    """Parsed by lxml without recovery (an ill-formed document raises) and by expat as well."""
    ET.fromstring(data)
    return etree.fromstring(data, etree.XMLParser(recover=False, resolve_entities=False, no_network=True))


def _report(text: str) -> FindReport:
    return FindReport(
        candidate_id="c-1",
        lat=47.39781,
        lon=8.54567,
        sigma_m=2.5,
        time=1732200000.5,
        prompt=text,
        confirmed_by=text[:64],
        vehicle_id="drone-1",
        mission_id="m-7",
        seen_at=None,
    )


@pytest.mark.parametrize("text", PAYLOADS.values(), ids=PAYLOADS.keys())
def test_hostile_cursor_on_target_event_is_well_formed_and_carries_the_text_as_text(text: str) -> None:
    data = find_event(_report(text), callsign="GCS\x01 one")
    event = _strict(data)
    assert not FORBIDDEN.search(data.decode("utf-8"))
    clean = FORBIDDEN.sub("", text)
    contact = event.find("detail/contact")
    assert contact is not None and contact.get("callsign") == f"FOUND: {clean}"[:80]
    remarks = event.findtext("detail/remarks") or ""
    assert clean[:64] in remarks and "GCS one" in remarks
    # The vehicle's markup stays text: the event holds only the elements the sender builds.
    assert {e.tag for e in event.iter()} <= {"event", "point", "detail", "contact", "remarks", "__group", "track"}


# The API strips control characters from the text fields of statuses and finds.


@pytest.fixture(scope="module")
def server(models_dir: Path) -> Iterator[BackgroundServer]:
    with BackgroundServer(create_app(backend_config(models_dir))) as running:
        yield running


def test_hostile_status_and_find_text_arrive_without_control_characters(server: BackgroundServer) -> None:
    auth = {"Authorization": f"Bearer {TOKENS['drone-1']}"}
    dirty = "Smith\x00 &\x01 Jones\x0b\ufffe"
    find = {"candidate_id": "c-1", "position": [47.4, 8.5], "sigma_m": 2.0, "time": 1732200000.0,
            "prompt": f"a man\x07 in {dirty}", "confirmed_by": dirty}  # fmt: skip
    status = {"mission_id": "m-1", "state": "FOUND\x1b[31m", "prompt": f"a man\x00 in red {dirty}",
              "reason": "why\x08", "find": find,
              "awaiting": {"candidate_id": "c-2", "box": [0, 0, 1, 1], "justification": "red\x00 shirt",
                           "unjudged": ["hat\x01"]}}  # fmt: skip
    answer = requests.post(f"{server.url}/v1/vehicles/drone-1/status", json=status, headers=auth, timeout=10)
    assert answer.status_code == 200, answer.text[:300]
    stored = requests.get(f"{server.url}/v1/vehicles/drone-1/status", headers=auth, timeout=10).json()
    assert stored["state"] == "FOUND[31m" and stored["reason"] == "why"
    assert stored["prompt"] == "a man in red Smith & Jones"
    assert stored["find"]["confirmed_by"] == "Smith & Jones" and stored["find"]["prompt"] == "a man in Smith & Jones"
    assert stored["awaiting"]["justification"] == "red shirt" and stored["awaiting"]["unjudged"] == ["hat"]
