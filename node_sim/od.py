"""The taxel node's object dictionary: loaded from ``eds/taxel_node.eds``, never re-declared.

The EDS (CiA 306 format; CiA 301 communication objects, CiA 404 analog-input objects and the
manufacturer objects 0x2000-0x2003 of the local detector, chapter eqs 1-4) is the single
source of the object dictionary. :func:`load_od` imports it with ``canopen.import_od``.

canopen 2.4.1 loses some EDS content at import (documented and pinned by
``tests/test_eds.py``): ``LowLimit``/``HighLimit`` of REAL32 entries are dropped (its parser
only reads integer limits). The node needs the REAL32 limits for its SDO range checks
(e.g. ζ ≥ 0 at 0x2001:1), so :func:`real_limits` reads exactly those keys from the same EDS
file with ``configparser``; nothing is duplicated in Python.

The index constants below name CiA 301/404 object indexes the code acts on (as canopen
itself does); their types, defaults, access and mapping rights all come from the EDS.

:class:`NodeObjects` is the glue between one node twin and its object dictionary: canopen's
``LocalNode`` (the OD, the data store, canopen's SDO server), typed reads and writes of the
data store, and the start-up values NMT reset-node / reset-communication restore. The
services of the node (:mod:`node_sim.nmt`, :mod:`.heartbeat`, :mod:`.sdo`, :mod:`.pdo`,
:mod:`.emcy`, :mod:`.sync`, :mod:`.detector`) read and write the OD through it.
"""

from __future__ import annotations

import configparser
import copy
import math
import re
from functools import lru_cache
from pathlib import Path

import canopen
from canopen.objectdictionary import ObjectDictionary, datatypes

from taxel_net.errors import ParameterError
from taxel_net.resources import eds_path, gripper_eds_path, patch_eds_path

EDS_PATH = eds_path()  # eds/taxel_node.eds, in the checkout or installed (taxel_net.resources)
# the shipped EDS of each device kind: what a user's EDS for that kind must declare (the twins
# implement every object of it)
SHIPPED_EDS = {"taxel node": EDS_PATH, "patch node": patch_eds_path(), "gripper drive": gripper_eds_path()}

# CiA 301 communication area (0x1000-0x1FFF): restored by NMT reset-communication
COMM_AREA = range(0x1000, 0x2000)
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
ERROR_FIELD = 0x1003          # pre-defined error field, sub 0 = number of errors (newest at sub 1)
COB_ID_SYNC = 0x1005
COB_ID_EMCY = 0x1014
CONSUMER_HEARTBEAT = 0x1016   # sub n: producer node-ID << 16 | time ms (0 = entry off)
HEARTBEAT_PRODUCER = 0x1017
IDENTITY = 0x1018
ERROR_BEHAVIOUR = 0x1029      # sub 1 communication error: 0 pre-operational, 1 no change, 2 stopped
SYNC_OVERFLOW = 0x1019        # synchronous counter overflow value: 0 = SYNC without counter, 2..240
TPDO_COMM = (0x1800, 0x1801)  # sub 1 COB-ID, 2 transmission type, 3 inhibit (100 µs), 5 event timer (ms), 6 SYNC start
TPDO_MAP = (0x1A00, 0x1A01)
# COB-ID entries (0x1005, 0x1014, 0x180x:1): CiA 301 bits
COB_INVALID = 0x80000000      # bit 31: PDO / EMCY not valid
COB_29BIT = 0x20000000
COB_NO_RTR = 0x40000000       # TPDO COB-ID bit 30: no RTR allowed (the twins never answer a remote frame)
# manufacturer area
LOCAL_DECISION = 0x2000       # u_i, INTEGER8 +1/-1 (eqs 2-3)
TAGGED_DECISION = 0x2003      # u_i in bits 0-1, SYNC counter mod 64 in bits 2-7 (TPDO1 with a SYNC counter)
SYNC_WINDOW = 0x1007          # synchronous window length, µs (0 = none)
DETECTOR = 0x2001             # sub 1 ζ mV, 2 N_i mV, 3 kind, 4 x, 5 y
FAULT_DETECTION = 0x2002      # sub 1 full scale mV, 2 stuck-sample count M (0 = off)
# CiA 404 analog input, channel 1 (sub 1)
AI_SCALING_FACTOR = 0x6126    # calibration slope m (eq 23)
AI_SCALING_OFFSET = 0x6127    # calibration intercept c (eq 23)
AI_INPUT_PV = 0x6130          # process value X_i in mV, REAL32
AI_STATUS = 0x6150            # bit 0 PV not valid, bit 1 positive overload, bit 2 negative overload

ZETA = (DETECTOR, 1)
NOISE_ESTIMATE = (DETECTOR, 2)
TAXEL_KIND = (DETECTOR, 3)
POS_X = (DETECTOR, 4)
POS_Y = (DETECTOR, 5)
FULL_SCALE = (FAULT_DETECTION, 1)
STUCK_SAMPLES = (FAULT_DETECTION, 2)


def check_eds(eds_path=EDS_PATH, device: str | None = None) -> Path:
    """The path of an EDS the twins can load, or :class:`~taxel_net.errors.ParameterError` (one
    line naming the file and ``device``, whose EDS it is: "taxel node" (the default), "patch
    node", "gripper drive"): a file that does not exist; :class:`~taxel_net.errors.EdsError` (a
    ParameterError naming the file and what is wrong or missing): one canopen cannot import or
    that is no valid CiA 306 file (:func:`taxel_net.eds_file.import_eds`), or that lacks an object
    of the shipped EDS of its device kind (:data:`SHIPPED_EDS`), declares it with another object,
    data or access type or PDO mapping, or without its default value
    (:func:`taxel_net.eds_file.check_objects`): the twins implement those objects. Values and
    limits may differ, objects may be added. Checked once per file version (a shipped EDS is
    not checked: ``tests/test_eds_input.py`` and ``tests/test_gripper_eds.py`` check them)."""
    path = Path(eds_path)
    if not path.is_file():
        whose = f"the {device} EDS" if device else "an EDS"
        raise ParameterError("eds", str(path), f"no such file: {whose} (CiA 306) must be an existing file")
    kind = device or "taxel node"
    if kind not in SHIPPED_EDS:
        raise ParameterError("device", device, f"one of {', '.join(SHIPPED_EDS)}")
    reference = SHIPPED_EDS[kind]
    if path.resolve() == reference.resolve():
        return path  # the shipped EDS of this kind (its tests check it)
    stat = path.stat()
    _check_against(str(path), stat.st_mtime_ns, stat.st_size, str(reference))
    return path


@lru_cache(maxsize=8)
def _check_against(path: str, mtime_ns: int, size: int, reference: str) -> None:
    from taxel_net.eds_file import check_objects, import_eds

    od = import_eds(path, 1)  # node-ID 1: the $NODEID defaults are read as a twin reads them
    check_objects(od, _reference_od(reference), path,
                  f"node-sim's twin implements every object of {Path(reference).name}")


@lru_cache(maxsize=3)
def _reference_od(reference: str) -> ObjectDictionary:
    return canopen.import_od(reference, 1)


def load_od(node_id: int, eds_path=EDS_PATH, device: str | None = None) -> ObjectDictionary:
    """Import the EDS of a ``device`` kind (:func:`check_eds`; the taxel node's by default) for
    ``node_id`` (1..127) with ``canopen.import_od``."""
    if not isinstance(node_id, int) or not 1 <= node_id <= 127:
        raise ParameterError("node_id", node_id, "CANopen node-ID must be an integer 1..127")
    path = check_eds(eds_path, device)
    return canopen.import_od(str(path), node_id)


@lru_cache(maxsize=8)
def _real_limits_cached(path: str, mtime: float) -> dict[tuple[int, int], tuple[float, float]]:
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",))
    parser.optionxform = str
    parser.read(path)
    limits: dict[tuple[int, int], tuple[float, float]] = {}
    for section in parser.sections():
        m = re.fullmatch(r"([0-9A-Fa-f]{4})(?:[Ss]ub([0-9A-Fa-f]+))?", section)
        if m is None:
            continue
        if int(parser.get(section, "DataType", fallback="0"), 0) not in datatypes.FLOAT_TYPES:
            continue
        low = parser.get(section, "LowLimit", fallback=None)
        high = parser.get(section, "HighLimit", fallback=None)
        if low is None and high is None:
            continue
        key = (int(m.group(1), 16), int(m.group(2), 16) if m.group(2) else 0)
        limits[key] = (float(low) if low is not None else -math.inf,
                       float(high) if high is not None else math.inf)
    return limits


def real_limits(eds_path=EDS_PATH) -> dict[tuple[int, int], tuple[float, float]]:
    """``{(index, subindex): (low, high)}`` of the REAL32/REAL64 entries of the EDS that carry
    ``LowLimit``/``HighLimit`` (the limits canopen 2.4.1 drops at import). The file's content is
    checked where its dictionary is loaded (:func:`load_od`, ``node_sim.patch.load_patch_od``:
    :func:`check_eds`, with the reference of its kind of node); a limit that is no number is an
    :class:`~taxel_net.errors.EdsError` here too."""
    from taxel_net.errors import EdsError

    path = Path(eds_path)
    if not path.is_file():
        raise ParameterError("eds", str(path), "the taxel node EDS file must exist (eds/taxel_node.eds)")
    try:
        return dict(_real_limits_cached(str(path), path.stat().st_mtime))
    except (configparser.Error, ValueError, UnicodeDecodeError) as exc:
        raise EdsError(path, "cannot be read: " + " ".join(f"{type(exc).__name__}: {exc}".split())) from None


def variable(od: ObjectDictionary, index: int, subindex: int = 0):
    """The ``ODVariable`` at ``index:subindex`` (sub-index ignored for a VAR object)."""
    obj = od[index]
    if isinstance(obj, canopen.objectdictionary.ODVariable):
        return obj
    return obj[subindex]


class NodeObjects:
    """The object dictionary of one node twin at run time (see module docstring).

    ``od`` defaults to the EDS imported for ``node_id``. ``local`` is canopen's ``LocalNode``
    (its ``data_store`` is replaced, not mutated, by the NMT resets: hold ``local``, never the
    store itself). ``real_limits`` are the EDS's REAL32 limits (:func:`real_limits`).
    """

    def __init__(self, node_id: int, od: ObjectDictionary | None = None, eds_path=EDS_PATH):
        self.od = od if od is not None else load_od(node_id, eds_path)
        self.real_limits = real_limits(eds_path)
        self.local = canopen.LocalNode(node_id, self.od)
        # LocalNode registers its NmtSlave's 0x1017 handler (which would start a python-can
        # periodic task per node); the node's heartbeat producer does that job itself.
        self.local._write_callbacks.clear()
        self._startup_store: dict[int, dict[int, bytes]] = {}

    def variable(self, index: int, subindex: int = 0):
        return variable(self.od, index, subindex)

    def read(self, index: int, subindex: int = 0):
        """Current value of ``index:subindex`` decoded with its EDS data type."""
        var = variable(self.od, index, subindex)
        return var.decode_raw(self.local.get_data(index, subindex))

    def store(self, index: int, subindex: int, value) -> None:
        """Write an application-owned value straight into the data store (EDS encoding)."""
        var = variable(self.od, index, subindex)
        self.local.data_store.setdefault(index, {})[subindex] = var.encode_raw(value)

    def store_raw(self, index: int, subindex: int, data: bytes) -> None:
        self.local.data_store.setdefault(index, {})[subindex] = data

    def discard(self, index: int, subindex: int) -> None:
        """Drop a stored value: ``index:subindex`` reads its EDS default again."""
        self.local.data_store.get(index, {}).pop(subindex, None)

    # -- start-up values (the node's non-volatile parameters)
    def save_startup(self) -> None:
        """The current values become the ones the NMT resets restore."""
        self._startup_store = copy.deepcopy(self.local.data_store)

    def restore_startup(self) -> None:
        """NMT reset node: the whole OD back to the start-up values."""
        self.local.data_store = copy.deepcopy(self._startup_store)

    def restore_communication(self) -> None:
        """NMT reset communication: only the communication area (0x1000-0x1FFF) back."""
        store = {i: s for i, s in self.local.data_store.items() if i not in COMM_AREA}
        store.update({i: dict(s) for i, s in copy.deepcopy(self._startup_store).items()
                      if i in COMM_AREA})
        self.local.data_store = store
