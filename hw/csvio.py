"""Fast, bounded-memory reading and writing of numeric CSV files (numpy and stdlib only).

Python's csv module builds a list of floats per row: a 10-million-row file (289 MB) took 46 s
and 2.8 GB. Here the file is read twice in blocks of ``BLOCK`` bytes: once to count its lines
(so the table is allocated once, at its final size), once to parse each block with
``np.fromstring(sep=",")`` after checking, per line, that it has as many commas as the header.
A block the fast path cannot take as it is (comments, blank lines, quotes, a bad value or field
count) goes through the csv module line by line, which keeps the exact rules and the one-line
errors of :func:`hw.expfile.read_csv_rows`. Memory: the table itself plus a few blocks.
"""

from __future__ import annotations

import csv
import io
import re
import sys
import time
import warnings

import numpy as np

from hw.textfiles import HEAD, check_decodes, not_text

#: Bytes parsed at a time (the temporaries are a few times this).
BLOCK = 1 << 22
#: Files at least this large report their progress on stderr.
PROGRESS_BYTES = 32 << 20


class CSVError(ValueError):
    """A line of the CSV that is not a row of numbers (the message names line and column)."""


def read_numeric_csv(path, name: str, progress=None):
    """(header, table, lines) of the CSV at ``path``: the header's names (stripped), a float64
    array of shape (rows, columns) and the 1-based line number of each row (int64 array), or
    (None, empty, empty) for a file without a header.

    Blank lines and lines starting with # or % (MATLAB's comment) are skipped, a UTF-8
    byte-order mark dropped, CRLF line ends and a comma at the end of every line (a
    spreadsheet's empty last column) accepted; a header separated by semicolons or tabs (a
    spreadsheet's regional export) reads every comma as a decimal point and every separator as a
    comma; names and numbers separated by spaces read as comma-separated ones. Raises
    :class:`CSVError` naming ``name``, the line and the column for a line with the wrong number
    of fields or a value that is not a number, and naming the cause and the fix for a file
    that is not CSV text (UTF-16, a workbook, :mod:`hw.textfiles`), has no header line, or is
    MATLAB's ``save -ascii`` output.
    ``progress`` (a callable taking a fraction 0-1, or None) defaults to a line on stderr for
    large files.
    """
    try:
        return _read_numeric_csv(path, name, progress)
    except csv.Error as exc:  # e.g. old Mac line ends (CR only): one line, not a traceback
        what = "its lines end in CR only" if "new-line" in str(exc) else str(exc)
        raise CSVError(f"{name}: {what}; save it as CSV with LF or CRLF line ends") from None


def _read_numeric_csv(path, name: str, progress=None):
    with open(path, "rb") as f:
        reason = not_text(f.read(HEAD), name)
        if reason:
            raise CSVError(reason)
        size = f.seek(0, io.SEEK_END)
        f.seek(0)
        header, lineno, start = _header(f, name)
        if header is None:
            return None, np.empty((0, 0)), np.empty(0, dtype=np.int64)
        header, lineno, start = _past_title(f, header, lineno, start, name)
        sep = next((c for c in ";\t" if len(header) == 1 and c in header[0]), None)
        if sep is None and _spaced(header, f, start):
            # Names and numbers separated by spaces (MATLAB's writematrix with a space, a
            # logger's text): each run of spaces a comma, as the CSV it stands for.
            f.seek(0)
            f = io.BytesIO(_SPACES.sub(b",", _EDGE_SPACES.sub(b"", f.read())))
            header, lineno, start = _header(f, name)
        elif sep is not None:
            # A spreadsheet's regional export (fields separated by semicolons, decimal commas)
            # or a tab-separated one: read as the CSV it stands for, every comma a decimal
            # point and every separator a comma (the line numbers stay). In memory: such
            # files are a spreadsheet's size.
            f.seek(0)
            f = io.BytesIO(f.read().translate(bytes.maketrans(b"," + sep.encode(), b".,")))
            header, lineno, start = _header(f, name)
        _check_header(header, lineno, name)
        if len(header) > 1 and header[-1] == "":  # "t,y,v,": the spreadsheet's empty column
            header = header[:-1]
        header, lineno, start = _with_units_row(f, header, lineno, start)
        ncols = len(header)
        capacity = _count_lines(f, start)
        table = np.empty((capacity, ncols))
        lines = np.empty(capacity, dtype=np.int64)
        if progress is None and size >= PROGRESS_BYTES:
            progress = _Progress(name, size)
        f.seek(start)
        rows = 0
        rest = b""
        done = start
        while True:
            block = f.read(BLOCK)
            data = rest + block
            if not data:
                break
            if block:
                cut = data.rfind(b"\n") + 1
                if cut == 0:  # one line longer than a block: read on
                    rest = data
                    continue
                data, rest = data[:cut], data[cut:]
            else:
                rest = b""
            values, numbers = _parse(data, ncols, lineno, header, name)
            k = values.shape[0]
            table[rows : rows + k] = values
            lines[rows : rows + k] = numbers
            rows += k
            lineno += data.count(b"\n") + (0 if data.endswith(b"\n") else 1)
            done += len(data)
            if progress is not None:
                progress(done / max(size, 1))
            if not block:
                break
    if progress is not None and hasattr(progress, "close"):
        progress.close()
    return header, table[:rows], lines[:rows]


def _header(f, name):
    """(header, number of the header's line, byte offset after it), skipping blank and #
    lines; a BOM before the first line is dropped."""
    lineno = 0
    while True:
        raw = f.readline()
        if not raw:
            return None, lineno, f.tell()
        lineno += 1
        if lineno == 1 and raw.startswith(b"\xef\xbb\xbf"):
            raw = raw[3:]
        reason = check_decodes(raw, f"{name}")
        if reason:
            raise CSVError(reason.replace(" line 1:", f" line {lineno}:", 1))
        text = raw.decode("utf-8")
        row = next(csv.reader([text]), [])
        if not row or not "".join(row).strip() or row[0].lstrip().startswith(COMMENTS):
            continue
        return [h.strip() for h in row], lineno, f.tell()


def _past_title(f, header, lineno, start, name):
    """(header, its line's number, where the data start) past a title line: one field (no
    separator in it) over a line of several names ("P 50 step - run 3" above "t,y,v"); as it
    was otherwise."""
    if len(header) != 1 or any(c in header[0] for c in ";\t") or " " not in header[0].strip():
        return header, lineno, start
    f.seek(start)
    names, below, after = _header(f, name)
    if names is None or len(names) < 2 or _numbers(names):
        return header, lineno, start
    return names, lineno + below, after


#: Runs of spaces and tabs (between fields), and those at a line's start or end.
_SPACES = re.compile(rb"[ \t]+")
_EDGE_SPACES = re.compile(rb"(?m)^[ \t]+|[ \t]+(?=\r?$)")


def _spaced(header, f, start) -> bool:
    """Whether a one-field header is names separated by spaces over lines of as many numbers
    separated by spaces (the first line after it says; ``f`` is left where it was)."""
    names = header[0].split() if len(header) == 1 else []
    if len(names) < 2 or _numbers(names):
        return False
    here = f.tell()
    f.seek(start)
    first = f.readline().decode("utf-8", "replace").split()
    f.seek(here)
    return len(first) == len(names) and _numbers(first)


#: Units a logger's second header line names (case as written); a line of them under the names
#: is their units (at least half of its fields among these and not "-" or "1", a missing value
#: or a one in a line of data; none longer than 6 characters).
_UNITS = frozenset({"s", "ms", "us", "µs", "m", "mm", "cm", "um", "µm", "V", "mV", "A", "mA",
                    "N", "m/s", "mm/s", "rad", "deg", "-", "1"})  # fmt: skip


def _with_units_row(f, header, lineno, start):
    """(header, its line's number, where the data start) with a units line under the names
    ("time,position,voltage" over "s,m,V", a logger's export) folded into the names ("time
    [s]"), so that a unit the reader knows converts (:func:`hw.expfile.si_factor`); as it was
    where the next line is no such line."""
    f.seek(start)
    raw = f.readline()
    row = next(csv.reader([raw.decode("utf-8", "replace")]), [])
    units = [u.strip().strip("[]()").strip() for u in row[: len(header)]]
    if (
        len(row) < len(header)
        or _numbers([u for u in units if u not in ("-", "1")])
        or any(len(u) > 6 for u in units)
        or sum(u in _UNITS and u not in ("-", "1") for u in units) * 2 < len(header)
    ):
        return header, lineno, start
    pairs = zip(header, units, strict=True)
    named = [h if not u or "[" in h or "(" in h else f"{h} [{u}]" for h, u in pairs]
    return named, lineno + 1, f.tell()


def _numbers(fields) -> bool:
    """Whether every field (at least one) is a number: a data line, not a header."""
    fields = [x for x in fields if x.strip()]
    return bool(fields) and all(_is_float(x) for x in fields)


def _check_header(header, lineno, name) -> None:
    """A first line of numbers is data: the file has no header (MATLAB's ``save -ascii``
    writes numbers separated by spaces, csvwrite and writematrix commas); Excel's ``sep=,``
    is a separator hint, not column names."""
    if header and header[0].lower().startswith("sep="):
        raise CSVError(
            f"{name} line {lineno}: {','.join(header)!r} is Excel's separator hint, not column "
            f"names; delete that line (the next one should name the columns, e.g. t,y,v)"
        )
    if len(header) == 1 and len(header[0].split()) > 1 and _numbers(header[0].split()):
        raise CSVError(
            f"{name} line {lineno}: numbers separated by spaces and no header line (MATLAB's "
            f"save -ascii?); write a CSV with a header instead, e.g. in MATLAB "
            f"writetable(array2table([t y v], 'VariableNames', {{'t','y','v'}}), '{name}')"
        )
    if _numbers(header):
        shown = ",".join(header[:4]) + (",..." if len(header) > 4 else "")
        raise CSVError(
            f"{name} line {lineno}: the first line holds numbers ({shown}), not column names: "
            f"the file has no header; add a first line naming the {len(header)} column(s), "
            f"e.g. t,y,v (time [s], position [m], voltage [V])"
        )


def _count_lines(f, start) -> int:
    f.seek(start)
    count = 1  # a last line without a newline
    while block := f.read(BLOCK):
        count += block.count(b"\n")
    return count


def _parse(data: bytes, ncols: int, lineno: int, header, name):
    """The rows of ``data`` (whole lines, the first being line ``lineno + 1``)."""
    body = data.replace(b"\r", b"") if b"\r" in data else data
    if body.endswith(b"\n"):
        body = body[:-1]
    n = body.count(b"\n") + 1 if body else 0
    fast = n and not any(c in body for c in (b"#", b"%", b'"', b"\n\n"))
    fast = fast and not body.startswith(b"\n")
    if fast:
        buf = np.frombuffer(body, dtype=np.uint8)
        ends = np.flatnonzero(buf == 10)
        commas = np.cumsum(buf == 44, dtype=np.int64)
        per_line = np.diff(np.concatenate([[0], commas[ends], [commas[-1]]]))
        # A blank cell (empty, or spaces only) would parse as -1.0 in np.fromstring: the slow
        # path names it instead.
        bare = body.translate(None, b" \t")
        blank = bare.startswith(b",") or bare.endswith(b",") or b",," in bare
        blank = blank or b"\n," in bare or b",\n" in bare
        if np.all(per_line == ncols - 1) and not blank:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    values = np.fromstring(body.replace(b"\n", b","), sep=",")
                except ValueError:
                    values = None
            if values is not None and values.size == n * ncols:
                return values.reshape(n, ncols), lineno + 1 + np.arange(n)
    return _parse_slowly(data, ncols, lineno, header, name)


def _parse_slowly(data: bytes, ncols, lineno, header, name):
    """The csv module's reading of ``data``, line by line, with the exact one-line errors."""
    rows, numbers = [], []
    reason = check_decodes(data, name)
    if reason:  # line numbers of the block, counted from the file's start
        head, _, tail = reason.partition(" line ")
        first, _, rest = tail.partition(":")
        raise CSVError(f"{head} line {lineno + int(first)}:{rest}")
    text = data.decode("utf-8")
    for i, row in enumerate(csv.reader(io.StringIO(text, newline="")), start=lineno + 1):
        if not row or not "".join(row).strip() or row[0].lstrip().startswith(COMMENTS):
            continue
        if len(row) == ncols + 1 and not row[-1].strip():
            row = row[:-1]  # a comma at the end of the line: an empty last column
        if len(row) != ncols:
            raise CSVError(
                f"{name} line {i}: {len(row)} fields, the header has {ncols}; "
                + (DECIMAL_COMMA if _split_decimals(row, ncols) else "fix that line")
            )
        try:
            rows.append([float(x) for x in row])
        except ValueError:
            bad = next(x for x in row if not _is_float(x))
            fix = DECIMAL_COMMA if _is_float(bad.replace(",", ".", 1)) else "fix that value"
            raise CSVError(
                f"{name} line {i}, column {header[row.index(bad)]}: {bad.strip()!r} is not a "
                f"number; {fix}"
            ) from None
        numbers.append(i)
    values = np.asarray(rows, dtype=float).reshape(len(rows), ncols)
    return values, np.asarray(numbers, dtype=np.int64)


#: A line whose first field starts with one of these is a comment: "#" (Python, the hardware
#: loop) and "%" (MATLAB's comment, fprintf'ed before the data).
COMMENTS = ("#", "%")

#: What to do about numbers written with a decimal comma (a spreadsheet's regional setting).
DECIMAL_COMMA = (
    "the numbers look written with decimal commas (0,5): save the file with a point as the "
    "decimal separator (0.5) and commas between the columns"
)


def _split_decimals(row, ncols) -> bool:
    """Whether ``row``'s extra fields are what decimal commas make of ``ncols`` numbers: whole
    numbers, up to twice as many as the header has columns."""
    return ncols < len(row) <= 2 * ncols and all(x.strip().lstrip("+-").isdigit() for x in row)


def _is_float(text) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


class _Progress:
    """``reading NAME (289 MB): 25% 50% 75% 100% in 3.1 s`` on stderr, one line."""

    def __init__(self, name, size, verb="reading", approx=False):
        self.start, self.next = time.perf_counter(), 0.25
        about = "about " if approx else ""
        print(f"{verb} {name} ({about}{size / 1e6:.0f} MB):", end="", file=sys.stderr, flush=True)

    def __call__(self, fraction):
        while fraction >= self.next and self.next <= 1.0:
            print(f" {self.next:.0%}", end="", file=sys.stderr, flush=True)
            self.next += 0.25

    def close(self):
        print(f" in {time.perf_counter() - self.start:.1f} s", file=sys.stderr, flush=True)


# ---------------------------------------------------------------- writing

#: Rows formatted at a time when writing (bounded memory: a block of text, not the file).
WRITE_ROWS = 1 << 16


def write_numeric_csv(f, names, arrays, *, name: str = "CSV", progress=None) -> None:
    """Write a header line and the columns ``arrays`` (1-D, one per name) to the text file
    ``f``, ``WRITE_ROWS`` rows at a time. Values are Python's shortest round-trip form
    (``repr``: read back, every float is the same float), so no copy of the whole table is
    made and a large file is written in seconds; ``progress`` as in :func:`read_numeric_csv`
    (default: a line on stderr when the output is about ``PROGRESS_BYTES`` or more)."""
    arrays = [np.asarray(a, dtype=float) for a in arrays]
    n = arrays[0].shape[0] if arrays else 0
    if progress is None and n * len(arrays) * 20 >= PROGRESS_BYTES:
        progress = _Progress(name, n * len(arrays) * 20, verb="writing", approx=True)
    f.write(",".join(names) + "\n")
    line = ",".join(["%r"] * len(arrays)) + "\n"
    for start in range(0, n, WRITE_ROWS):
        block = np.column_stack([a[start : start + WRITE_ROWS] for a in arrays])
        # One format operation per block: C-level, twice as fast as a join per row.
        f.write((line * block.shape[0]) % tuple(block.ravel().tolist()))
        if progress is not None:
            progress(min(1.0, (start + WRITE_ROWS) / n))
    if progress is not None and hasattr(progress, "close"):
        progress.close()
