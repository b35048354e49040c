"""What the project's EDS generators share: the CiA 306 writer, the CiA 301 communication profile and
the file skeleton.

``eds/make_patch_eds.py`` (``eds/taxel_patch.eds``) and ``eds/make_gripper_eds.py``
(``eds/gripper_drive.eds``) import this module; they are run as ``python eds/make_x.py``, so this
directory is on ``sys.path``. ``eds/taxel_node.eds`` is hand-written and has no generator.

Every sub-object is written out (no ``CompactSubObj``: canopen 2.4.1 gives a compact array's sub 0
no value, and eds-utils / objdictgen read explicit sub-objects), so ``canopen.import_od`` sees
every entry and sub 0 of every ARRAY gives its number of entries.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

# CiA 301 data types (the DataType of an object)
INTEGER8, INTEGER16, INTEGER32 = 0x0002, 0x0003, 0x0004
UNSIGNED8, UNSIGNED16, UNSIGNED32 = 0x0005, 0x0006, 0x0007
REAL32, VISIBLE_STRING = 0x0008, 0x0009

MANDATORY = [0x1000, 0x1001, 0x1018]   # CiA 301: device type, error register, identity


class Writer:
    """The lines of an EDS, one ``[section]`` of ``key=value`` entries after another."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def section(self, name: str, **entries) -> None:
        self.lines.append(f"[{name}]")
        for key, value in entries.items():
            self.lines.append(f"{key}={value}")
        self.lines.append("")

    def var(self, name: str, parameter: str, data_type: int, access: str, default, mappable: bool = False,
            low=None, high=None) -> None:
        entries = {"ParameterName": parameter, "ObjectType": "0x7", "DataType": f"0x{data_type:04X}",
                   "AccessType": access, "DefaultValue": default}
        if low is not None:
            entries["LowLimit"] = low
        if high is not None:
            entries["HighLimit"] = high
        entries["PDOMapping"] = int(mappable)
        self.section(name, **entries)

    def compound(self, index: int, parameter: str, object_type: int, subs: int) -> None:
        self.section(f"{index:04X}", ParameterName=parameter, ObjectType=f"0x{object_type:X}", SubNumber=subs + 1)

    def array(self, index: int, parameter: str, entry: str, n: int, data_type: int, access: str, default,
              mappable: bool = False, low=None, high=None) -> None:
        self.compound(index, parameter, 0x8, n)
        self.var(f"{index:04X}sub0", "Number of entries", UNSIGNED8, "ro", n)
        for sub in range(1, n + 1):
            self.var(f"{index:04X}sub{sub:X}", f"{entry} {sub}", data_type, access, default, mappable, low, high)

    def tpdo_communication(self, k: int, cob) -> None:
        """TPDO ``k + 1``'s communication parameter 0x1800 + k (CiA 301): synchronous (type 1)."""
        index = 0x1800 + k
        self.section(f"{index:04X}", ParameterName=f"TPDO communication parameter {k + 1}", ObjectType="0x9",
                     SubNumber=6)
        self.var(f"{index:04X}sub0", "Highest sub-index supported", UNSIGNED8, "ro", 6)
        self.var(f"{index:04X}sub1", "COB-ID used by TPDO", UNSIGNED32, "rw", cob)
        self.var(f"{index:04X}sub2", "Transmission type", UNSIGNED8, "rw", 1)
        self.var(f"{index:04X}sub3", "Inhibit time", UNSIGNED16, "rw", 0)
        self.var(f"{index:04X}sub5", "Event timer", UNSIGNED16, "rw", 0)
        self.var(f"{index:04X}sub6", "SYNC start value", UNSIGNED8, "rw", 0)

    def mapping(self, index: int, parameter: str, default: list[int], entries: int) -> None:
        """A PDO mapping record of ``entries`` entries, the first ``len(default)`` of them mapped
        (each ``index << 16 | sub << 8 | bits``), the rest 0."""
        self.compound(index, parameter, 0x9, entries)
        self.var(f"{index:04X}sub0", "Number of mapped objects", UNSIGNED8, "rw", len(default), low=0, high=entries)
        for sub in range(1, entries + 1):
            value = default[sub - 1] if sub <= len(default) else 0
            self.var(f"{index:04X}sub{sub:X}", f"Mapping entry {sub}", UNSIGNED32, "rw", f"0x{value:08X}")


def communication_profile(w: Writer, *, device_type: int, device_name: str, product_code: int,
                          cycle_period_us: int | None = None, communication_error: int = 0,
                          emcy_inhibit: bool = False) -> list[int]:
    """Write the CiA 301 objects 0x1000-0x1200 every generated node has; return the optional ones written.

    What differs between the nodes: the device type 0x1000, the device name 0x1008, the product
    code 0x1018:2, the communication cycle period 0x1006 in µs (not written when None) and the
    error behaviour 0x1029:1 on a communication error (0: to PRE-OPERATIONAL, 1: no state change),
    whether the node has the EMCY inhibit time 0x1015 (``emcy_inhibit``; default 0: none).
    """
    w.var("1000", "Device type", UNSIGNED32, "ro", f"0x{device_type:08X}")
    w.var("1001", "Error register", UNSIGNED8, "ro", 0, mappable=True)
    w.compound(0x1003, "Pre-defined error field", 0x8, 8)
    w.var("1003sub0", "Number of errors", UNSIGNED8, "rw", 0)
    for sub in range(1, 9):
        w.var(f"1003sub{sub}", f"Standard error field {sub}", UNSIGNED32, "ro", 0)
    w.var("1005", "COB-ID SYNC", UNSIGNED32, "rw", "0x00000080")
    if cycle_period_us is not None:
        w.var("1006", "Communication cycle period", UNSIGNED32, "rw", cycle_period_us)
    w.var("1007", "Synchronous window length", UNSIGNED32, "rw", 0)
    w.var("1008", "Manufacturer device name", VISIBLE_STRING, "const", device_name)
    w.var("1014", "COB-ID EMCY", UNSIGNED32, "rw", "$NODEID+0x80")
    if emcy_inhibit:
        w.var("1015", "Inhibit time EMCY", UNSIGNED16, "rw", 0)
    w.compound(0x1016, "Consumer heartbeat time", 0x8, 2)
    w.var("1016sub0", "Highest sub-index supported", UNSIGNED8, "ro", 2)
    for sub in (1, 2):
        w.var(f"1016sub{sub}", f"Consumer heartbeat time {sub}", UNSIGNED32, "rw", 0)
    w.var("1017", "Producer heartbeat time", UNSIGNED16, "rw", 0)
    w.compound(0x1018, "Identity object", 0x9, 4)
    w.var("1018sub0", "Highest sub-index supported", UNSIGNED8, "ro", 4)
    w.var("1018sub1", "Vendor-ID", UNSIGNED32, "ro", "0x00000000")
    w.var("1018sub2", "Product code", UNSIGNED32, "ro", f"0x{product_code:08X}")
    w.var("1018sub3", "Revision number", UNSIGNED32, "ro", "0x00010000")
    w.var("1018sub4", "Serial number", UNSIGNED32, "ro", "0x00000000")
    w.var("1019", "Synchronous counter overflow value", UNSIGNED8, "rw", 0, low=0, high=240)
    w.compound(0x1029, "Error behaviour", 0x8, 1)
    w.var("1029sub0", "Highest sub-index supported", UNSIGNED8, "ro", 1)
    w.var("1029sub1", "Communication error", UNSIGNED8, "rw", communication_error, low=0, high=2)
    w.compound(0x1200, "SDO server parameter", 0x9, 2)
    w.var("1200sub0", "Highest sub-index supported", UNSIGNED8, "ro", 2)
    w.var("1200sub1", "COB-ID client to server", UNSIGNED32, "ro", "$NODEID+0x600")
    w.var("1200sub2", "COB-ID server to client", UNSIGNED32, "ro", "$NODEID+0x580")
    optional = [0x1003, 0x1005, 0x1006, 0x1007, 0x1008, 0x1014, 0x1015, 0x1016, 0x1017, 0x1019, 0x1029, 0x1200]
    return [index for index in optional
            if (index != 0x1006 or cycle_period_us is not None) and (index != 0x1015 or emcy_inhibit)]


def render(body: Writer, *, optional: list[int], manufacturer: list[int], comments: list[str], file_name: str,
           description: str, product_name: str, product_code: int, order_code: str, rpdos: int, tpdos: int) -> str:
    """The whole EDS: [FileInfo], [DeviceInfo], [DummyUsage], [Comments], the object lists, then ``body``."""
    w = Writer()
    w.section("FileInfo", FileName=file_name, FileVersion=1, FileRevision=1, EDSVersion="4.0",
              Description=description,
              CreationTime="12:00PM", CreationDate="01-01-2025", CreatedBy="taxel-can",
              ModificationTime="12:00PM", ModificationDate="01-01-2025", ModifiedBy="taxel-can")
    w.section("DeviceInfo", VendorName="taxel-can (no CiA vendor-ID assigned)", VendorNumber="0x00000000",
              ProductName=product_name, ProductNumber=f"0x{product_code:08X}",
              RevisionNumber="0x00010000", OrderCode=order_code,
              BaudRate_10=0, BaudRate_20=0, BaudRate_50=0, BaudRate_125=1, BaudRate_250=1, BaudRate_500=1,
              BaudRate_800=0, BaudRate_1000=1, SimpleBootUpMaster=0, SimpleBootUpSlave=1, Granularity=8,
              DynamicChannelsSupported=0, GroupMessaging=0, NrOfRXPDO=rpdos, NrOfTXPDO=tpdos, LSS_Supported=0)
    w.section("DummyUsage", **{f"Dummy{i:04d}": 0 for i in range(1, 8)})
    w.section("Comments", Lines=len(comments), **{f"Line{i}": line for i, line in enumerate(comments, start=1)})
    for name, indexes in (("MandatoryObjects", MANDATORY), ("OptionalObjects", optional),
                          ("ManufacturerObjects", manufacturer)):
        w.section(name, SupportedObjects=len(indexes),
                  **{str(i): f"0x{index:04X}" for i, index in enumerate(indexes, start=1)})
    return "\n".join(w.lines + body.lines)


def main(argv: list[str], out: Path, render: Callable[[], str], generator: str) -> int:
    """Write ``out`` from ``render()``; with ``--check`` only compare (exit 1 if it differs)."""
    text = render()
    if "--check" in argv:
        same = out.is_file() and out.read_text() == text
        print(f"{out}: {'up to date' if same else f'differs from {generator}'}")
        return 0 if same else 1
    out.write_text(text)
    print(f"wrote {out} ({len(text)} bytes)")
    return 0
