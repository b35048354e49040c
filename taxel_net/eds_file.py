"""A user's EDS file (CiA 306), imported with canopen - or one line saying what is wrong.

``canopen.import_od`` lets most of a malformed EDS through as a traceback (``configparser``'s
``ParsingError`` / ``NoOptionError``, ``UnicodeDecodeError``, ``ValueError`` of ``int()``),
and some of it silently: a ``DefaultValue``, ``LowLimit`` or ``HighLimit`` that is not a number
of its data type is dropped (the object then has no default), an object with an unknown
``ObjectType`` is left out, a file without ``[DeviceInfo]`` gives a log line and an empty
dictionary. :func:`import_eds` turns each of these into one :class:`~taxel_net.errors.EdsError`
naming the file and the section, key and value (or the line), and :func:`check_objects` says
which object of a reference EDS a user's lacks or declares otherwise (the node twins implement
the shipped EDS's objects: ``node_sim.od.check_eds``).

Loaded through here: node-sim's ``--eds`` (``node_sim.od``, ``node_sim.patch``), the centre's
EDS (``fusion_center.service.fusion_service``) and ``fusion-center dcf --eds``.
"""

from __future__ import annotations

import configparser
import locale
import logging
import math
import re
import struct
from pathlib import Path

from .errors import EdsError, one_line

ACCESS_TYPES = ("ro", "wo", "rw", "rwr", "rww", "const")  # CiA 306 4.6.3.2 AccessType
_OBJECT_SECTION = re.compile(r"([0-9A-Fa-f]{4})(?:[Ss]ub([0-9A-Fa-f]+))?")
_NUMBER_KEYS = ("ObjectType", "DataType", "PDOMapping", "SubNumber", "CompactSubObj")
_LOGGER = "canopen.objectdictionary.eds"


def _type_name(data_type: int | None) -> str:
    from canopen.objectdictionary import datatypes

    names = {v: k for k, v in vars(datatypes).items() if k.isupper() and isinstance(v, int)}
    return names.get(data_type, f"0x{data_type:04X}" if isinstance(data_type, int) else "none")


class _Capture(logging.Handler):
    """canopen's warnings during an import (no [DeviceInfo], an unknown data type): errors here."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def _parser(text: str) -> configparser.RawConfigParser:
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",))  # as canopen reads it
    parser.optionxform = str
    parser.read_string(text)
    return parser


def _read_text(path: Path) -> str:
    """The file's text as canopen opens it (``open(path)``: the locale's encoding)."""
    encoding = locale.getpreferredencoding(False)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise EdsError(path, f"cannot be read: {exc.strerror or exc}") from None
    if b"\x00" in data:
        raise EdsError(path, f"not a text file: a NUL byte at offset {data.index(0)} (an EDS is CiA 306 text)")
    if not data.strip():
        raise EdsError(path, "empty file (an EDS is CiA 306 text: [FileInfo], [DeviceInfo] and a section per object)")
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        raise EdsError(path, f"not a text file: byte 0x{data[exc.start]:02X} at offset {exc.start} is not "
                             f"{encoding} (an EDS is CiA 306 text)") from None


def _syntax_problem(text: str) -> str | None:
    """What configparser refuses in the text, on one line, or None."""
    try:
        _parser(text)
    except configparser.MissingSectionHeaderError as exc:
        line = text.splitlines()[exc.lineno - 1] if 0 < exc.lineno <= len(text.splitlines()) else ""
        return f"line {exc.lineno}: {line.strip()[:60]!r} comes before any [section] (not an EDS?)"
    except configparser.ParsingError as exc:
        lineno = exc.errors[0][0]
        line = text.splitlines()[lineno - 1] if 0 < lineno <= len(text.splitlines()) else ""
        return f"line {lineno}: {line.strip()[:60]!r} is not a Key=Value line (cut short?)"
    except configparser.DuplicateSectionError as exc:
        return f"line {exc.lineno}: section [{exc.section}] appears twice"
    except configparser.DuplicateOptionError as exc:
        return f"line {exc.lineno}: key {exc.option} appears twice in [{exc.section}]"
    except configparser.Error as exc:
        return one_line(exc)
    return None


_DEVICE_INFO_NUMBERS = ("VendorNumber", "ProductNumber", "RevisionNumber", "NrOfRXPDO", "NrOfTXPDO",
                        "SimpleBootUpMaster", "SimpleBootUpSlave", "Granularity", "DynamicChannelsSupported",
                        "GroupMessaging", "LSS_Supported")


def _value_problem(parser: configparser.RawConfigParser) -> str | None:
    """A key canopen converts with ``int(value, 0)`` whose value is no number, on one line, or None."""
    for section in parser.sections():
        if _OBJECT_SECTION.fullmatch(section):
            keys = _NUMBER_KEYS
        elif section == "DeviceInfo":
            keys = [k for k in parser.options(section) if k.startswith("BaudRate_") or k in _DEVICE_INFO_NUMBERS]
        elif section == "Comments":
            keys = ("Lines",)
        elif re.fullmatch(r"[Dd]ummy[Uu]sage", section):
            keys = parser.options(section)
        else:
            continue
        for key in keys:
            if not parser.has_option(section, key):
                continue
            value = parser.get(section, key)
            try:
                int(value, 0)
            except ValueError:
                return f"[{section}] {key}={value!r} is not a number"
    return None


def _variables(od):
    from canopen.objectdictionary import ODVariable

    for obj in od.values():
        if isinstance(obj, ODVariable):
            yield obj
        else:
            yield from obj.values()


def _section_of(var, sections: dict[str, str]) -> str:
    """The section that declares ``var`` (as written in the file), e.g. ``1018sub3``."""
    from canopen.objectdictionary import ODArray, ODRecord

    if isinstance(var.parent, (ODRecord, ODArray)):
        key = f"{var.index:04X}SUB{var.subindex:X}"
        if key not in sections and var.subindex == 1 and f"{var.index:04X}" in sections:
            key = f"{var.index:04X}"  # CompactSubObj: the array's own section
    else:
        key = f"{var.index:04X}"
    return sections.get(key, key)


def _limit(text: str, data_type: int) -> float:
    from canopen.objectdictionary import datatypes

    if data_type in datatypes.FLOAT_TYPES:
        value = float(text)
        if math.isnan(value):
            raise ValueError(text)
        return value
    return int(text.replace(" ", ""), 0)


def _variable_problem(var, raw: dict[str, dict[str, str]], sections: dict[str, str],
                      node_id: int | None) -> str | None:
    """A variable's data type, access type, default or limits that are no value of their kind."""
    from canopen.objectdictionary import datatypes

    section = _section_of(var, sections)
    where = f"[{section}]"
    written = raw.get(section.upper(), {})
    try:
        declared = int(written["DataType"], 0)
    except (KeyError, ValueError):
        declared = var.data_type
    # a DataType above 0x1B names a type the EDS defines ([<type>sub1], which canopen reads);
    # without that section canopen takes DOMAIN, with a log line
    undefined = isinstance(declared, int) and declared > 0x1B and f"{declared:X}SUB1" not in sections
    if undefined or not isinstance(var.data_type, int) or not 1 <= var.data_type <= 0x1B:
        shown = written.get("DataType", var.data_type)
        return f"{where} DataType={shown!r} is neither a CiA 301 basic data type (0x0001..0x001B) nor one the EDS defines"
    if var.access_type not in ACCESS_TYPES:
        return f"{where} AccessType={var.access_type!r}: one of {', '.join(ACCESS_TYPES)}"
    default_text = getattr(var, "default_raw", None)  # set by canopen when DefaultValue is there
    if default_text is not None:
        if var.default is None:
            if not (var.relative and node_id is None):
                return f"{where} DefaultValue={default_text!r} is not a {_type_name(var.data_type)} value"
        else:
            try:
                packer = var.STRUCT_TYPES.get(var.data_type)
                if packer is not None:
                    packer.pack(int(var.default) if var.data_type in datatypes.INTEGER_TYPES else var.default)
                elif var.data_type == datatypes.VISIBLE_STRING:
                    var.default.encode("ascii")
            except (ValueError, OverflowError, TypeError, UnicodeError, struct.error):
                return f"{where} DefaultValue={default_text!r} does not fit {_type_name(var.data_type)}"
    if var.data_type in datatypes.NUMBER_TYPES:
        for key, text in written.items():
            if key not in ("LowLimit", "HighLimit"):
                continue
            try:
                _limit(text, var.data_type)
            except ValueError:
                return f"{where} {key}={text!r} is not a {_type_name(var.data_type)} value"
    return None


_RAW_KEYS = ("ObjectType", "DataType", "LowLimit", "HighLimit")
OBJECT_TYPES = (0x2, 0x5, 0x6, 0x7, 0x8, 0x9)  # CiA 306 ObjectType: DOMAIN, DEFTYPE, DEFSTRUCT, VAR, ARRAY, RECORD


def _raw_keys(text: str) -> dict[str, dict[str, str]]:
    """``ObjectType``, ``DataType``, ``LowLimit``, ``HighLimit`` as written, by section name in
    upper case (canopen leaves out an object of an ObjectType it does not know, replaces a
    DataType it does not know by DOMAIN, drops limits it cannot read and reads none of a REAL
    type): one pass over the lines, split as configparser splits them (``key=value`` or
    ``key: value``, a ``;`` comment after a space)."""
    found: dict[str, dict[str, str]] = {}
    section = ""
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("[") and stripped.endswith("]"):
            section = stripped[1:-1].upper()
        elif stripped.startswith(_RAW_KEYS):
            key, _, value = stripped.partition("=") if "=" in stripped else stripped.partition(":")
            key = key.strip()
            if key in _RAW_KEYS:
                found.setdefault(section, {})[key] = re.split(r"\s;", value)[0].strip()
    return found


def _explain(text: str, exc: BaseException) -> str:
    """What canopen's import stumbled on, on one line (configparser's own reading first)."""
    problem = _syntax_problem(text)
    if problem is not None:
        return problem
    if isinstance(exc, configparser.NoOptionError):
        return f"[{exc.section}] has no {exc.option} (mandatory, CiA 306)"
    if isinstance(exc, configparser.NoSectionError):
        return f"no [{exc.section}] section"
    problem = _value_problem(_parser(text))
    if problem is not None:
        return problem
    return f"cannot be read: {one_line(exc)}"


def import_eds(path, node_id: int | None = None):
    """``canopen.import_od(path, node_id)`` of an EDS file, checked: :class:`EdsError` (one line:
    the file, then the line, or the section, key and value) for a file that is missing, empty,
    binary, not CiA 306 text (``Key=Value`` lines under ``[sections]``), without ``[DeviceInfo]``,
    with an object section lacking a mandatory key (``ParameterName``, ``DataType``,
    ``AccessType``), with a number key (``ObjectType``, ``DataType``, ``PDOMapping``,
    ``SubNumber``, ``[DeviceInfo]``'s) that is no number, an ``ObjectType`` or ``AccessType``
    CiA 306 does not have, a ``DataType`` that is neither a CiA 301 basic type nor one the file
    defines, or a ``DefaultValue`` / ``LowLimit`` /
    ``HighLimit`` that is no value of its data type (``$NODEID`` defaults: with ``node_id``).
    The checks of a valid file cost one pass over its lines besides canopen's import."""
    import canopen

    p = Path(path)
    if not p.is_file():
        raise EdsError(p, "not found" if not p.exists() else "not a file")
    text = _read_text(p)
    capture = _Capture()
    log = logging.getLogger(_LOGGER)
    propagate = log.propagate
    log.addHandler(capture)
    log.propagate = False
    try:
        od = canopen.import_od(str(p), node_id)
    except Exception as exc:  # noqa: BLE001 - any content: one line naming the file
        raise EdsError(p, _explain(text, exc)) from None
    finally:
        log.removeHandler(capture)
        log.propagate = propagate
    if any("DeviceInfo" in message for message in capture.messages):
        raise EdsError(p, "no [DeviceInfo] section (mandatory, CiA 306): is it an EDS?")
    raw = _raw_keys(text)
    sections = {name.upper(): name for name in _section_names(text)}
    for key, written in raw.items():
        if "ObjectType" in written and _OBJECT_SECTION.fullmatch(key):
            try:
                object_type = int(written["ObjectType"], 0)
            except ValueError:
                object_type = None
            if object_type not in OBJECT_TYPES:
                raise EdsError(p, f"[{sections.get(key, key)}] ObjectType={written['ObjectType']!r}: one of "
                                  "0x2 DOMAIN, 0x5 DEFTYPE, 0x6 DEFSTRUCT, 0x7 VAR, 0x8 ARRAY, 0x9 RECORD (CiA 306)")
    for var in _variables(od):
        problem = _variable_problem(var, raw, sections, node_id)
        if problem is not None:
            raise EdsError(p, problem)
    if capture.messages:
        raise EdsError(p, capture.messages[0])
    return od


def _section_names(text: str) -> list[str]:
    return [line.strip()[1:-1] for line in text.splitlines() if line.strip().startswith("[") and line.strip().endswith("]")]


def check_objects(od, reference, path, what: str) -> None:
    """:class:`EdsError` naming the first object of the ``reference`` dictionary that ``od`` (of
    the EDS file ``path``) lacks or declares with another object type, data type, access type
    or PDO mapping, or without the default value the reference gives it; ``what`` says who needs
    them (e.g. ``node-sim's taxel node implements every object of taxel_node.eds``)."""
    from canopen.objectdictionary import ODArray, ODRecord, ODVariable

    def kind(obj) -> str:
        return "VAR" if isinstance(obj, ODVariable) else "ARRAY" if isinstance(obj, ODArray) else \
            "RECORD" if isinstance(obj, ODRecord) else type(obj).__name__

    for index, ref in reference.items():
        if not isinstance(index, int):
            continue
        obj = od.get(index)
        if obj is None:
            raise EdsError(path, f"object 0x{index:04X} is missing ({what})")
        if kind(obj) != kind(ref):
            raise EdsError(path, f"object 0x{index:04X} is {kind(obj)}, not {kind(ref)} ({what})")
        pairs = [(ref, obj)] if isinstance(ref, ODVariable) else []
        if not pairs:
            for sub, ref_var in ref.items():
                if not isinstance(sub, int):
                    continue
                if sub not in obj.subindices:
                    raise EdsError(path, f"object 0x{index:04X}:{sub} is missing ({what})")
                pairs.append((ref_var, obj.subindices[sub]))
        for ref_var, var in pairs:
            name = f"object 0x{index:04X}:{ref_var.subindex}"
            for key, mine, theirs in (("DataType", var.data_type, ref_var.data_type),
                                      ("AccessType", var.access_type, ref_var.access_type),
                                      ("PDOMapping", int(var.pdo_mappable), int(ref_var.pdo_mappable))):
                if mine != theirs:
                    shown = (lambda v: f"0x{v:04X} ({_type_name(v)})") if key == "DataType" else repr
                    raise EdsError(path, f"{name} has {key}={shown(mine)}, not {shown(theirs)} ({what})")
            if getattr(ref_var, "default_raw", None) is not None and getattr(var, "default_raw", None) is None:
                raise EdsError(path, f"{name} has no DefaultValue ({what})")
