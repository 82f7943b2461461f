"""SMI iView X remote command interface: the text-line codec, free of I/O (docs/protocols.md, SMI).

One line per UDP datagram (section 1.1): a mnemonic ET_xxx and arguments separated by runs of
whitespace, double-quoted strings kept whole. ET_SPL sample lines follow the ET_FRM format (section
1.3): with eye type b every per-eye specifier carries two values, left then right. Fixation events
(section 1.4) and validation replies (section 1.2) have fixed shapes. Text is Latin-1, so any byte
decodes and the degree sign of ET_VLS is one byte; the grammar then decides what is valid. Every
violation raises SmiError naming the line, which a transport counts as malformed.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, fields
from typing import Annotated, ClassVar, Self, get_origin, get_type_hints

MAX_LINE_BYTES = 4096  # far above any real line; longer datagrams are dropped by the transports
MAX_FORMAT_CHARS = 1024  # keeps every ET_SPL line of a format under MAX_LINE_BYTES
MAX_COUNTER = 2**64  # %TS, %TU and %SC range (section 1.3)

COUNTERS = frozenset({"TS", "TU", "SC"})  # one non-negative integer per line
PER_EYE = frozenset({"SX", "SY", "DX", "DY", "PX", "PY", "CX", "CY", "EX", "EY", "EZ"})  # one float per eye
SPECIFIERS = COUNTERS | PER_EYE | {"ET"}

GAZE_FORMAT = "%TU %ET %SX %SY"  # what the smi:// driver asks for, and the emulator's default
RED_FORMATS = (  # formats of the real RED captures (section 7, items 1 and 3)
    "%TU %ET %SX %SY %DX %DY %EX %EY %EZ %PX %PY",
    "%ET %TS %SX %SY %EX %EY %EZ",
)

# one way to match each number: "\d+\.?\d*" splits a run of digits in n ways, and a long run that then
# fails to match took seconds (quadratic backtracking)
_NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_INT = r"\d+"
_EYE = "[lrb]"
_MNEMONIC = re.compile(r"ET_[A-Z]{3}")
_TOKEN = re.compile(r'\s*(?:"([^"]*)"|([^\s"]+))(?=\s|$)')
_CONTROL = re.compile(r"[\x00-\x08\x0a-\x1f\x7f]")
_SPECIFIER = re.compile(r"(%[A-Z]{2})")
_SEPARATOR = re.compile(r"[^\w.+-]")  # a character no value contains
_QUOTED = frozenset({"ET_FRM", "ET_SAV"})  # string arguments clients send in quotes (section 1.1)


class SmiError(ValueError):
    """A line that breaks the SMI grammar."""


def decode(data: bytes) -> str:
    """The text of one datagram without its line end (\\n, \\r\\n or the serial \\t\\n); one line only."""
    text = data.decode("latin-1").strip(" \t\r\n")
    if _CONTROL.search(text):
        raise SmiError(f"control character in line {text[:80]!r}")
    return text


def encode(text: str) -> bytes:
    """One line as a datagram payload, newline-terminated."""
    return (text + "\n").encode("latin-1")


def parse_line(text: str) -> tuple[str, tuple[str, ...]]:
    """(mnemonic, arguments) of a line; quoted arguments keep their spaces and lose their quotes."""
    args: list[str] = []
    pos, end = 0, len(text.rstrip())
    while pos < end:
        m = _TOKEN.match(text, pos)
        if m is None:
            raise SmiError(f"quotes must enclose whole arguments: {text[:80]!r}")
        args.append(m.group(1) if m.group(1) is not None else m.group(2))
        pos = m.end()
    if not args or text.lstrip().startswith('"') or not _MNEMONIC.fullmatch(args[0]):
        raise SmiError(f"line does not start with a mnemonic ET_XXX: {text[:80]!r}")
    return args[0], tuple(args[1:])


def command(mnemonic: str, *args: object) -> str:
    """A command line; string arguments of ET_FRM and ET_SAV, and any with spaces, are quoted."""
    if not _MNEMONIC.fullmatch(mnemonic):
        raise SmiError(f"not a mnemonic: {mnemonic!r}")
    words = [mnemonic]
    for arg in map(str, args):
        if '"' in arg or _CONTROL.search(arg):
            raise SmiError(f"argument {arg!r} cannot be sent (quote or control character)")
        words.append(f'"{arg}"' if mnemonic in _QUOTED or not arg or re.search(r"\s", arg) else arg)
    return " ".join(words)


def int_args(args: tuple[str, ...], lo: int, hi: int, counts: tuple[int, ...] = (1,)) -> list[int]:
    """Integer arguments within [lo, hi]; how many there may be is one of `counts`."""
    if len(args) not in counts:
        raise SmiError(f"expected {' or '.join(map(str, counts))} arguments, got {len(args)}")
    if not all(a.isascii() and a.isdigit() and len(a) <= 18 for a in args):
        raise SmiError(f"arguments must be non-negative integers, got {' '.join(args)!r}")
    values = [int(a) for a in args]
    if not all(lo <= v <= hi for v in values):
        raise SmiError(f"arguments {' '.join(args)} are outside {lo}..{hi}")
    return values


def _number(value: float) -> str:
    """Shortest text that reads back as the same float; integral values without a decimal point."""
    value = float(value)
    if not math.isfinite(value):
        raise SmiError(f"cannot send a non-finite value {value}")
    return str(int(value)) if value.is_integer() and abs(value) < 2**53 else repr(value)


def _float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise SmiError(f"value {text!r} is out of range")
    return value


def _counter(text: str) -> int:
    value = int(text)
    if value > MAX_COUNTER:
        raise SmiError(f"counter {text} exceeds 2^64")
    return value


def _body(line: str, mnemonic: str) -> str:
    """The text after the mnemonic of a line that must start with it."""
    text = line.strip()
    rest = text[len(mnemonic) :]
    if not text.startswith(mnemonic) or (rest and not rest[0].isspace()):
        raise SmiError(f"expected an {mnemonic} line, got {line[:80]!r}")
    return rest.strip()


@dataclass(frozen=True)
class SplSample:
    """The fields of one ET_SPL line by specifier name without %: counters as int, per-eye values as
    tuples of one float (eye l or r) or two (eye b: left, right). eye is None for a monocular line
    whose format has no %ET."""

    eye: str | None
    values: Mapping[str, int | tuple[float, ...]]

    @property
    def timestamp_us(self) -> int | None:
        """%TU, else %TS in microseconds, else None."""
        if "TU" in self.values:
            return int(self.values["TU"])
        return int(self.values["TS"]) * 1000 if "TS" in self.values else None


def _literal_pattern(text: str) -> str:
    """A literal of the format as a pattern: runs of whitespace match any run of whitespace."""
    return "".join(r"\s+" if chunk.isspace() else re.escape(chunk) for chunk in re.split(r"(\s+)", text) if chunk)


@dataclass(frozen=True)
class SampleFormat:
    """An ET_FRM format (section 1.3): "%XX" specifiers and literal text, in order."""

    text: str
    tokens: tuple[str, ...]
    patterns: tuple[tuple[int, re.Pattern[str]], ...] = field(repr=False, compare=False)  # (values per eye, regex)

    @classmethod
    def parse(cls, text: str) -> SampleFormat:
        text = text.strip()
        if len(text) > MAX_FORMAT_CHARS or _CONTROL.search(text) or '"' in text or not text.isascii():
            raise SmiError(f"a format is printable ASCII without quotes, at most {MAX_FORMAT_CHARS} characters")
        tokens = tuple(t for t in _SPECIFIER.split(text) if t)
        names = [t[1:] for t in tokens if t.startswith("%")]
        for t in tokens:
            if "%" in t and not (_SPECIFIER.fullmatch(t) and t[1:] in SPECIFIERS):
                raise SmiError(f"unknown specifier in {t!r}; known: {' '.join('%' + s for s in sorted(SPECIFIERS))}")
        if not names:
            raise SmiError(f"format {text!r} has no specifier")
        if len(set(names)) < len(names):
            raise SmiError(f"format {text!r} repeats a specifier")
        at = [i for i, t in enumerate(tokens) if t.startswith("%")]
        for i, j in zip(at, at[1:], strict=False):
            if not _SEPARATOR.search("".join(tokens[i + 1 : j])):
                raise SmiError(f"specifiers {tokens[i]} and {tokens[j]} need a separator such as a space, ',' or ':'")
        eyes = (2, 1) if PER_EYE.intersection(names) else (1,)
        return cls(text, tokens, tuple((n, re.compile(cls._pattern(tokens, n))) for n in eyes))

    @staticmethod
    def _pattern(tokens: tuple[str, ...], eyes: int) -> str:
        parts = []
        for t in tokens:
            name = t[1:] if t.startswith("%") else None
            if name is None:
                parts.append(_literal_pattern(t))
            elif name == "ET":
                parts.append(f"({_EYE})")
            elif name in COUNTERS:
                parts.append(f"({_INT})")
            else:
                parts.append(r"\s+".join([f"({_NUMBER})"] * eyes))
        return "".join(parts)

    @property
    def specifiers(self) -> tuple[str, ...]:
        return tuple(t[1:] for t in self.tokens if t.startswith("%"))

    def parse_line(self, line: str) -> SplSample:
        """The fields of an ET_SPL line in this format; SmiError when the line does not match it."""
        body = _body(line, "ET_SPL")
        for eyes, pattern in self.patterns:
            if m := pattern.fullmatch(body):
                return self._sample(iter(m.groups()), eyes, line)
        raise SmiError(f"ET_SPL line does not match format {self.text!r}: {line[:120]!r}")

    def _sample(self, groups: Iterator[str], eyes: int, line: str) -> SplSample:
        eye, values = None, {}
        for name in self.specifiers:
            if name == "ET":
                eye = next(groups)
            elif name in COUNTERS:
                values[name] = _counter(next(groups))
            else:
                values[name] = tuple(_float(next(groups)) for _ in range(eyes))
        if len(self.patterns) == 2:  # the format has per-eye values: their count must fit the eye type
            if eye is None:
                eye = "b" if eyes == 2 else None
            elif (eye == "b") != (eyes == 2):
                raise SmiError(f"eye type {eye} with {eyes} value(s) per eye: {line[:120]!r}")
        return SplSample(eye, values)

    def format_line(self, sample: SplSample) -> str:
        """The ET_SPL line of a sample in this format (values the format does not name are left out)."""
        eyes = 2 if sample.eye == "b" else 1
        words = []
        for t in self.tokens:
            name = t[1:] if t.startswith("%") else None
            if name is None:
                words.append(t)
                continue
            if name == "ET":
                if sample.eye not in ("l", "r", "b"):
                    raise SmiError(f"format {self.text!r} needs an eye type l, r or b, got {sample.eye!r}")
                words.append(sample.eye)
                continue
            if name not in sample.values:
                raise SmiError(f"sample has no value for %{name}")
            value = sample.values[name]
            if name in COUNTERS:
                if not isinstance(value, int) or not 0 <= value <= MAX_COUNTER:
                    raise SmiError(f"%{name} must be an integer within 0..2^64, got {value!r}")
                words.append(str(value))
            elif len(value) != eyes:
                raise SmiError(f"%{name} needs {eyes} value(s) for eye type {sample.eye}, got {len(value)}")
            else:
                words.append(" ".join(map(_number, value)))
        return "ET_SPL " + "".join(words)


@dataclass(frozen=True)
class _Field:
    """One word of a fixed-shape line: its pattern (one group), how it is read and how it is written."""

    pattern: str
    read: Callable[[str], object]
    write: Callable[[object], str]


# a fixed-shape line's field types: the value's type, annotated with how its word reads and writes
_Eye = Annotated[str, _Field(f"({_EYE})", str, str)]
_Time = Annotated[int, _Field(f"({_INT})", _counter, str)]
_Number = Annotated[float, _Field(f"({_NUMBER})", _float, _number)]
# read with a unit suffix such as the degree sign, written with the degree sign
_Degrees = Annotated[float, _Field(rf"({_NUMBER})[^\s\d]{{0,3}}", _float, lambda v: _number(v) + "\u00b0")]


class _FixedLine:
    """A line of fixed shape: `mnemonic`, then one whitespace-separated word per dataclass field, read and
    written as the field's type says (`shape`, in field order)."""

    mnemonic: ClassVar[str]
    shape: ClassVar[tuple[_Field, ...]]

    def __init_subclass__(cls) -> None:
        hints = get_type_hints(cls, include_extras=True).values()
        cls.shape = tuple(h.__metadata__[0] for h in hints if get_origin(h) is Annotated)

    @classmethod
    def parse(cls, line: str) -> Self:
        words = _body(line, cls.mnemonic).split()
        matches = [re.fullmatch(f.pattern, w) for f, w in zip(cls.shape, words, strict=False)]
        if len(words) != len(cls.shape) or not all(matches):
            raise SmiError(f"{cls.mnemonic} line does not have the shape of docs/protocols.md, SMI: {line[:120]!r}")
        return cls(*(f.read(m.group(1)) for f, m in zip(cls.shape, matches, strict=True)))

    def line(self) -> str:
        values = (getattr(self, f.name) for f in fields(self))
        return " ".join([self.mnemonic, *(f.write(v) for f, v in zip(self.shape, values, strict=True))])


@dataclass(frozen=True)
class FixationStart(_FixedLine):
    """ET_FIX <eye> <start_us> <x> <y>: a fixation began (section 1.4)."""

    eye: _Eye
    start_us: _Time
    x: _Number
    y: _Number

    mnemonic: ClassVar = "ET_FIX"


@dataclass(frozen=True)
class FixationEnd(_FixedLine):
    """ET_EFX <eye> <start_us> <end_us> <duration_ms> <x> <y>: a fixation ended (section 1.4)."""

    eye: _Eye
    start_us: _Time
    end_us: _Time
    duration_ms: _Time
    x: _Number
    y: _Number

    mnemonic: ClassVar = "ET_EFX"

    @classmethod
    def parse(cls, line: str) -> FixationEnd:
        event = super().parse(line)
        if event.end_us < event.start_us:
            raise SmiError(f"fixation ends before it starts: {line[:120]!r}")
        return event


def parse_event(line: str) -> FixationStart | FixationEnd:
    """An ET_FIX or ET_EFX event line."""
    return FixationEnd.parse(line) if line.lstrip().startswith("ET_EFX") else FixationStart.parse(line)


@dataclass(frozen=True)
class Validation(_FixedLine):
    """ET_VLS <eye> <x> <y> <d> <xd>° <yd>°: accuracy at a validation target (px), in degrees (section 1.2)."""

    eye: _Eye
    x: _Number
    y: _Number
    deviation_deg: _Number
    x_deg: _Degrees
    y_deg: _Degrees

    mnemonic: ClassVar = "ET_VLS"
