"""What an input file really is, when it is not the UTF-8 text it should be (stdlib only).

Students open their recordings in Excel, Notepad and MATLAB and save them from there: a file
named run.csv may be UTF-16 (Notepad's "Unicode", Excel's "Unicode Text"), an Excel workbook,
a MATLAB .mat file, or text in a Windows code page. A decoder error ("'utf-8' codec can't
decode byte 0xff") names none of these; :func:`not_text` looks at the first bytes and says
which it is and how to save it as UTF-8 text. Paths typed the Windows way ("runs\\run.csv" in
a TOML basic string, where ``\\r`` is a carriage return) are mended by :func:`portable_path`.
"""

from __future__ import annotations

import os

#: Bytes looked at to recognise a file.
HEAD = 4096
#: UTF-8's byte-order mark (Notepad, Excel's "CSV UTF-8"): dropped, the text read.
UTF8_BOM = b"\xef\xbb\xbf"

_SAVE_UTF8 = "save it as UTF-8 text (Notepad: Save As, Encoding UTF-8; Excel: CSV UTF-8)"


def not_text(head: bytes, name) -> str | None:
    """Why the file whose first bytes are ``head`` is not UTF-8 text, and the fix, as one
    line starting with ``name``; None when it reads as UTF-8 text (a BOM allowed)."""
    if head.startswith((b"\xff\xfe", b"\xfe\xff")) or _utf16_without_bom(head):
        return f"{name} is saved as UTF-16 (Unicode text), not UTF-8; {_SAVE_UTF8}"
    if head.startswith(b"PK\x03\x04"):
        return (
            f"{name} is an Excel workbook (.xlsx) or another zip file, not CSV text; in Excel "
            f"use File > Save As > CSV UTF-8 (comma delimited) and give that file"
        )
    if head.startswith(b"\xd0\xcf\x11\xe0"):
        return (
            f"{name} is an old Excel workbook (.xls), not CSV text; in Excel use File > Save As "
            f"> CSV UTF-8 (comma delimited) and give that file"
        )
    if head.startswith(b"MATLAB") or head.startswith(b"\x89HDF"):
        return (
            f"{name} is a MATLAB .mat file, not text; map its variables in the experiment's "
            f'TOML ([data] y = "{os.path.basename(str(name))}:variable")'
        )
    if b"\x00" in head:
        return f"{name} is a binary file, not text; give a CSV file (UTF-8 text)"
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not merely a character cut at the end of the head
            return _not_utf8(name, head, exc)
    return None


def check_decodes(data: bytes, name) -> str | None:
    """The one-line reason ``data`` (a whole file or block) is not UTF-8, or None."""
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        return _not_utf8(name, data, exc)
    return None


def _not_utf8(name, data: bytes, exc: UnicodeDecodeError) -> str:
    line = data.count(b"\n", 0, exc.start) + 1
    byte = data[exc.start : exc.start + 1].hex()
    return (
        f"{name} line {line}: byte 0x{byte} is not UTF-8 (the file is in a Windows or Mac "
        f"code page, e.g. a degree sign or an accent); {_SAVE_UTF8}"
    )


def _utf16_without_bom(head: bytes) -> bool:
    """ASCII text written as UTF-16 has a zero byte in every other place."""
    pairs = len(head) // 2
    if pairs < 2:
        return False
    even, odd = head[0 : 2 * pairs : 2], head[1 : 2 * pairs : 2]
    return even.count(0) > 0.8 * pairs or odd.count(0) > 0.8 * pairs


#: Control characters a TOML basic string makes of a Windows path's backslashes
#: ("runs\run.csv": \r; "C:\tests\new.csv": \t and \n), mapped back to what was typed.
_ESCAPES = {"\r": "\\r", "\t": "\\t", "\n": "\\n", "\b": "\\b", "\f": "\\f"}


def portable_path(text: str) -> str:
    """A path as the user typed it, usable here: control characters that TOML made of
    backslash escapes turned back into the backslash and letter, then (where the separator
    is "/") backslashes read as separators. "runs\\run.csv" -> "runs/run.csv"."""
    typed = "".join(_ESCAPES.get(ch, ch) for ch in text)
    if os.sep == "/":
        typed = typed.replace("\\", "/")
    return typed
