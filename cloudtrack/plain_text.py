"""Text a vehicle or an operator wrote, made safe to carry anywhere: without control characters.

XML 1.0 forbids U+0000-U+0008, U+000B, U+000C, U+000E-U+001F, U+FFFE, U+FFFF and lone surrogates (a
Cursor-on-Target event or a KML file holding one is ill-formed, and TAK drops it); the C1 controls and
DEL are no text either. Tab, line feed and carriage return stay. Used by the API's text fields (stripped
on the way in) and by every document built from stored text (stripped again on the way out: a store
written before the API stripped still holds them).
"""

from __future__ import annotations

import re

_CONTROL = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f\ud800-\udfff\ufffe\uffff]")


def without_controls(text: str) -> str:
    """`text` without the characters above (nothing else changes)."""
    return _CONTROL.sub("", text)
