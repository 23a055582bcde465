"""The GCS mission protocol on the companion: prompt codec, commands, camera tracking, status to the GCS."""

from __future__ import annotations

import math

import pytest

from behaviors.geometry import Box
from behaviors.mission_commands import (
    AbortMission,
    RejectCandidate,
    StartMission,
    StopTracking,
    TrackRectangle,
)
from cloudtrack.gcs_protocol import (
    CHUNK_TEXT_BYTES,
    PROMPT_PAYLOAD_TYPE,
    PromptAssembler,
    decode_chunk,
    encode_prompt,
    parse_prompt_text,
    statustext_chunks,
    validate_prompt,
)
from tests.mavlink_harness import MainLoop, autopilot, gcs, receive_until, vehicle_link, wait_for


def _is_ack(command: int):  # type: ignore[no-untyped-def]
    return lambda m: m.get_type() == "COMMAND_ACK" and m.command == command


def test_prompt_round_trip_through_chunks() -> None:
    prompt = "injured man in a gray shirt lying next to a red backpack, near the river bank " * 3
    payloads = encode_prompt(9, "person", prompt)
    assert len(payloads) == math.ceil(len(("person|" + prompt.strip()).encode()) / CHUNK_TEXT_BYTES) > 1
    assert all(len(p) <= 128 for p in payloads)
    assembler = PromptAssembler()
    for payload in reversed(payloads):  # order on the wire does not matter
        chunk = decode_chunk(PROMPT_PAYLOAD_TYPE, payload)
        assert chunk is not None
        assembler.add(chunk, 0.0)
    text = assembler.take(9, len(payloads), sum(len(p) - 4 for p in payloads))
    assert parse_prompt_text(text) == ("person", prompt.strip())


def test_malformed_prompts_are_refused_with_a_reason() -> None:
    assert validate_prompt("   ") == "the prompt is empty"
    assert "control characters" in validate_prompt("man\x00in gray")
    assert "400" in validate_prompt("x" * 401)
    assert "superset" in validate_prompt("a man", "per|son")
    with pytest.raises(ValueError):
        parse_prompt_text(b"\xff\xfe|man")
    with pytest.raises(ValueError):
        parse_prompt_text(b"no separator")
    assert decode_chunk(1234, b"\x01\x00\x00\x01abc") is None  # someone else's TUNNEL payload
    assert decode_chunk(PROMPT_PAYLOAD_TYPE, b"\x01\x00\x05\x02abc") is None  # index beyond count
    with pytest.raises(LookupError, match="chunks \\[1\\] missing"):
        assembler = PromptAssembler()
        first = decode_chunk(PROMPT_PAYLOAD_TYPE, encode_prompt(3, "", "a" * 200)[0])
        assert first is not None
        assembler.add(first, 0.0)
        assembler.take(3, 2, 201)


def test_long_status_is_split_into_linked_chunks() -> None:
    chunks = statustext_chunks(
        "CANDIDATE 2: yes, gray shirt, lying on the ground next to a bicycle; confirm?"
    )
    assert [seq for _, seq in chunks] == [0, 1] and all(len(c) <= 50 for c, _ in chunks)


@pytest.mark.parametrize(("length", "pieces"), [(1, [1]), (50, [50]), (51, [50, 1]), (100, [50, 50, 0])])
def test_a_long_status_ends_with_a_short_chunk_the_receiver_can_tell(length: int, pieces: list[int]) -> None:
    """A receiver takes the chunk without 50 bytes (a null terminator) as the last (`GcsSession.join_statustext`):
    a 100-byte line needs an empty third chunk, or the GCS would wait for the rest forever; one chunk alone
    (id 0) needs none."""
    chunks = statustext_chunks("x" * length)
    assert [len(c) for c, _ in chunks] == pieces and [seq for _, seq in chunks] == list(range(len(pieces)))
    assert b"".join(c for c, _ in chunks) == b"x" * length


def _send_prompt(ground, mission_id: int, superset: str, prompt: str) -> tuple[int, int]:  # type: ignore[no-untyped-def]
    payloads = encode_prompt(mission_id, superset, prompt)
    for payload in payloads:
        padded, n = list(payload) + [0] * (128 - len(payload)), len(payload)
        ground.send(lambda m, p=padded, n=n: m.tunnel_send(1, 191, PROMPT_PAYLOAD_TYPE, n, p))
    return len(payloads), sum(len(p) - 4 for p in payloads)


def test_mission_commands_over_mavlink_through_the_autopilot() -> None:
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link), gcs(sim) as ground:
        count, length = _send_prompt(ground, 7, "person", "woman in a green jacket")
        ground.send(lambda m: m.command_long_send(1, 191, 31010, 0, 7, count, 1, length, 0, 0, 0))
        ack = receive_until(ground, _is_ack(31010))
        assert ack is not None and ack.result == 0 and (ack.target_system, ack.target_component) == (255, 190)
        status = receive_until(ground, lambda m: m.get_type() == "STATUSTEXT" and "MISSION 7" in m.text)
        assert status is not None and "woman in a green jacket" in status.text
        ground.send(lambda m: m.command_long_send(1, 191, 31013, 0, 3, 0, 0, 0, 0, 0, 0))
        ground.send(lambda m: m.command_long_send(1, 191, 31011, 0, 0, 0, 0, 0, 0, 0, 0))
        assert receive_until(ground, _is_ack(31011)) is not None
        assert wait_for(lambda: len(link._commands) >= 3)
        assert link.commands() == [
            StartMission("woman in a green jacket", "person", allow_engage=True, mission_id="7"),
            RejectCandidate("3"),
            AbortMission("gcs"),
        ]
        # a start whose chunks never arrived: FAILED (resend), with a readable reason
        ground.send(lambda m: m.command_long_send(1, 191, 31010, 0, 8, 1, 0, 10, 0, 0, 0))
        assert receive_until(ground, _is_ack(31010)).result == 4
        # a malformed prompt: DENIED and a STATUSTEXT saying why; nothing reaches the main loop
        bad = [1, 9, 0, 1] + list(b"person|man\x01in gray")
        ground.send(
            lambda m: m.tunnel_send(1, 191, PROMPT_PAYLOAD_TYPE, len(bad), bad + [0] * (128 - len(bad)))
        )
        ground.send(lambda m: m.command_long_send(1, 191, 31010, 0, 9, 1, 0, len(bad) - 4, 0, 0, 0))
        assert receive_until(ground, _is_ack(31010)).result == 2
        first = receive_until(
            ground, lambda m: m.get_type() == "STATUSTEXT" and m.text.startswith("START REFUSED")
        )
        rest = receive_until(
            ground, lambda m: m.get_type() == "STATUSTEXT" and m.id == first.id and m.chunk_seq == 1
        )
        assert "control characters" in first.text + rest.text  # long lines arrive as linked chunks
        assert link.commands() == []


@pytest.mark.parametrize(
    "component", [100, 191]
)  # the camera identity QGroundControl uses, and the companion's
def test_camera_tracking_protocol(component: int) -> None:
    def command(cmd: int, *params: float):  # type: ignore[no-untyped-def]
        p = list(params) + [0.0] * (7 - len(params))
        ground.send(lambda m: m.command_long_send(1, component, cmd, 0, *p))
        ack = receive_until(ground, _is_ack(cmd))
        assert ack is not None and ack.get_srcComponent() == component  # answered by the addressed component
        return ack.result

    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link), gcs(sim) as ground:
        camera_hb = receive_until(
            ground, lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 100, 3.0
        )
        assert camera_hb is not None and camera_hb.type == 30  # MAV_TYPE_CAMERA: QGC finds it among 100-105
        assert command(512, 259) == 0  # REQUEST_MESSAGE(CAMERA_INFORMATION)
        info = receive_until(ground, lambda m: m.get_type() == "CAMERA_INFORMATION")
        assert info is not None and info.get_srcComponent() == component
        assert info.flags & 1024 and info.flags & 512  # tracking rectangle + point
        assert (info.resolution_h, info.resolution_v) == (640, 480)
        assert command(2005, 0.25, 0.5, 0.5, 1.0) == 0
        assert command(2004, 0.5, 0.5, 0.1) == 0
        assert command(2005, 0.8, 0.5, 0.2, 1.0) == 2  # corners swapped: DENIED
        assert command(2010) == 0
        if component == 100:
            assert command(31012) == 3  # mission commands only to the companion component: UNSUPPORTED
        commands = link.commands()
        assert commands[0] == TrackRectangle(Box(160.0, 240.0, 160.0, 240.0))
        assert isinstance(commands[1], TrackRectangle) and commands[1].box.cx == pytest.approx(320.0)
        assert commands[1].box.w == pytest.approx(128.0) and commands[1].box.h == pytest.approx(128.0)
        assert commands[2:] == [StopTracking()]
        # while tracking the camera component streams CAMERA_TRACKING_IMAGE_STATUS, normalised
        link.report_tracking(Box(320, 120, 64, 120), (640, 480))
        status = receive_until(ground, lambda m: m.get_type() == "CAMERA_TRACKING_IMAGE_STATUS")
        assert status is not None and status.get_srcComponent() == 100
        assert status.tracking_status == 1 and status.tracking_mode == 2
        assert (
            status.rec_top_x,
            status.rec_top_y,
            status.rec_bottom_x,
            status.rec_bottom_y,
        ) == pytest.approx((0.5, 0.25, 0.6, 0.5))
        assert status.point_x == pytest.approx(0.55)
        link.report_tracking(None, (640, 480))
        idle = receive_until(
            ground, lambda m: m.get_type() == "CAMERA_TRACKING_IMAGE_STATUS" and m.tracking_status == 0
        )
        assert idle is not None


def test_status_values_and_status_request() -> None:
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link), gcs(sim) as ground:
        link.send_value("confidence", 0.83)
        value = receive_until(ground, lambda m: m.get_type() == "NAMED_VALUE_FLOAT")
        assert value.name == "confidence" and value.value == pytest.approx(0.83)
        with pytest.raises(ValueError):
            link.send_value("much_too_long_name", 1.0)
        link.send_status("CANDIDATE 2: yes, gray shirt, lying on the ground next to a bicycle; confirm?")
        parts = [
            receive_until(ground, lambda m: m.get_type() == "STATUSTEXT" and m.get_srcComponent() == 191)
            for _ in range(2)
        ]
        assert parts[0].chunk_seq == 0 and parts[1].chunk_seq == 1 and parts[0].id == parts[1].id != 0
        assert (parts[0].text + parts[1].text).endswith("confirm?")
        ground.send(
            lambda m: m.command_long_send(1, 191, 31014, 0, 0, 0, 0, 0, 0, 0, 0)
        )  # USER_5: repeat status
        assert receive_until(ground, _is_ack(31014)).result == 0
        assert (
            receive_until(ground, lambda m: m.get_type() == "STATUSTEXT" and m.text.startswith("CANDIDATE 2"))
            is not None
        )


def test_well_formed_but_nonsensical_commands_are_denied_not_crashing() -> None:
    nan = math.nan
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link), gcs(sim) as ground:
        ground.send(lambda m: m.tunnel_send(1, 191, PROMPT_PAYLOAD_TYPE, 255, [1, 4, 0, 1] + [0xFF] * 124))
        for command, params in (
            (31010, (nan, 1, 0, 10)),  # start: mission id NaN
            (31010, (4, 1, 0, 1e9)),  # start: absurd length
            (31010, (4, 1, 0, 124)),  # start: the chunk above (payload_length 255 > 128) is not UTF-8
            (31012, (-3.5,)),  # confirm: not a candidate number
            (2005, (nan, 0.1, 0.5, 0.5)),  # rectangle with NaN corner
            (512, (33,)),  # REQUEST_MESSAGE for something the companion does not provide
        ):
            p = list(params) + [0.0] * (7 - len(params))
            ground.send(lambda m, c=command, p=p: m.command_long_send(1, 191, c, 0, *p))
            ack = receive_until(ground, _is_ack(command))
            assert ack is not None and ack.result == 2, (command, params)
        assert link.commands() == []
        assert all(t.is_alive() for t in link._threads)


def test_the_starts_on_find_is_one_of_four_codes() -> None:
    """The start's param5: 0 not set, 1 continue, 2 hold, 3 return; anything else is DENIED, nothing started."""
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link), gcs(sim) as ground:
        for mission, fifth in ((5, 9.0), (6, 1.5), (7, -1.0)):
            count, length = _send_prompt(ground, mission, "person", "a man in a green shirt")
            ground.send(
                lambda m, n=mission, c=count, k=length, f=fifth: m.command_long_send(
                    1, 191, 31010, 0, n, c, 0, k, f, 0, 0
                )
            )
            ack = receive_until(ground, _is_ack(31010))
            assert ack is not None and ack.result == 2, fifth
        count, length = _send_prompt(ground, 8, "person", "a man in a green shirt")
        ground.send(lambda m: m.command_long_send(1, 191, 31010, 0, 8, count, 0, length, 2, 0, 0))
        ack = receive_until(ground, _is_ack(31010))
        assert ack is not None and ack.result == 0
        assert wait_for(lambda: len(link._commands) >= 1)
        assert link.commands() == [
            StartMission("a man in a green shirt", "person", mission_id="8", on_find="hold")
        ]
