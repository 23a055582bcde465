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
    assert {e.tag for e in event.iter()} <= {
        "event",
        "point",
        "detail",
        "contact",
        "remarks",
        "__group",
        "track",
    }


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
    assert (
        stored["find"]["confirmed_by"] == "Smith & Jones"
        and stored["find"]["prompt"] == "a man in Smith & Jones"
    )
    assert stored["awaiting"]["justification"] == "red shirt" and stored["awaiting"]["unjudged"] == ["hat"]


# Items 1 and 2: the KML download of every payload, through the API, as a rescuer's tool reads it.

KML = "{http://www.opengis.net/kml/2.2}"
SUPERVISOR_AUTH = {"Authorization": "Bearer token-supervisor"}


def _report_find(
    server: BackgroundServer,
    vehicle: str,
    mission: str,
    candidate: str,
    prompt: str,
    by: str,
    position: tuple[float, float] = (47.4, 8.5),
) -> requests.Response:
    find = {"candidate_id": candidate, "position": list(position), "sigma_m": 2.0, "time": 1732200000.0,
            "prompt": prompt, "confirmed_by": by}  # fmt: skip
    status = {"mission_id": mission, "state": "CONFIRMED", "prompt": prompt, "find": find}
    answer = requests.post(
        f"{server.url}/v1/vehicles/{vehicle}/status",
        json=status,
        headers={"Authorization": f"Bearer {TOKENS[vehicle]}"},
        timeout=10,
    )
    return answer


def _html_elements(text: str) -> list[str]:
    """The elements a KML reader's HTML balloon would make of a description."""
    from lxml import html

    return [e.tag for e in html.fragment_fromstring(text, create_parent="div").iter() if e.tag != "div"]


@pytest.mark.parametrize("text", PAYLOADS.values(), ids=PAYLOADS.keys())
def test_hostile_kml_of_any_text_parses_and_carries_it_as_text(server: BackgroundServer, text: str) -> None:
    mission = f"kml-{abs(hash(text)) % 10**8}"
    answer = _report_find(server, "drone-1", mission, "c-1", text, (text + " & Jones")[:64])
    if "\ud800" in text:  # no JSON text can hold a lone surrogate: refused, naming the fields
        assert answer.status_code == 422 and "find" in answer.text and "string_unicode" in answer.text
        text = FORBIDDEN.sub("", text)
        answer = _report_find(server, "drone-1", mission, "c-1", text, (text + " & Jones")[:64])
    assert answer.status_code == 200, answer.text[:300]
    # another vehicle's find of the same mission id: another person, 1 km away (one person seen by two
    # vehicles is one find)
    other = _report_find(server, "drone-2", mission, "c-2", "a woman in a red jacket", "gcs", (47.409, 8.5))
    assert other.status_code == 200
    answer = requests.get(
        f"{server.url}/v1/missions/{mission}/finds.kml", headers=SUPERVISOR_AUTH, timeout=30
    )
    assert answer.status_code == 200, answer.text[:300]
    assert not FORBIDDEN.search(answer.content.decode("utf-8"))
    document = _strict(answer.content)
    placemarks = {p.findtext(f"{KML}ExtendedData/{KML}Data[@name='candidate_id']/{KML}value"): p
                  for p in document.iter(f"{KML}Placemark") if p.find(f"{KML}Point") is not None}  # fmt: skip
    assert set(placemarks) == {"c-1", "c-2"}, set(placemarks)
    find = placemarks["c-1"]
    # The vehicle's words are the Data values, as text, exactly as stored (the API took the controls out).
    clean = FORBIDDEN.sub("", text)
    assert find.findtext(f"{KML}ExtendedData/{KML}Data[@name='prompt']/{KML}value") == clean
    # Nothing it wrote became an element: one name (ours), one Point, no element the vehicle named.
    assert [e.text for e in find.iter(f"{KML}name")] == [find.findtext(f"{KML}name")]
    assert (find.findtext(f"{KML}name") or "").startswith("FOUND ")
    assert len(list(find.iter(f"{KML}Point"))) == 1
    assert not {etree.QName(e).localname for e in find.iter()} & {"img", "a", "FAKE"}
    # The balloon is plain text: its description makes no HTML element but line breaks, and links no address.
    description = find.findtext(f"{KML}description") or ""
    assert set(_html_elements(description)) <= {"br"}, description
    assert "://" not in description and "href" not in _html_elements(description)
    styles = {style.get("id"): style for style in document.iter(f"{KML}Style")}
    style = styles[(find.findtext(f"{KML}styleUrl") or "").lstrip("#")]
    assert style.findtext(f"{KML}BalloonStyle/{KML}text") == "$[description]"
