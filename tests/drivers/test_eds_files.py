"""The EDS files the project ships (config/can, tests/data) are consistent in the sense
of CiA 306 (the EDS format), as an EDS checker would require: every object listed in
exactly one of the three object lists and every listed object described, the lists'
counts right, manufacturer objects (0x2000-0x5FFF) only in [ManufacturerObjects], each
variable with its name, data type, access type and PDO mapping flag, each array or record
with SubNumber sections and sub0, default values inside their limits, the PDO counts of
[DeviceInfo] those of the file, and the [FileInfo] file name the file's."""

from __future__ import annotations

import configparser
import re
from pathlib import Path

import canopen
import pytest

ROOT = Path(__file__).resolve().parents[2]
EDS_FILES = sorted((ROOT / "config").rglob("*.eds")) + sorted(
    (ROOT / "tests" / "data").glob("*.eds")
)
LISTS = ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects")
ACCESS = {"ro", "wo", "rw", "rwr", "rww", "const"}
DATA_TYPES = {*range(0x0001, 0x000E), *range(0x000F, 0x001C)}  # CiA 301 static data types
VAR, ARRAY, RECORD = 0x7, 0x8, 0x9
OBJECT = re.compile(r"^[0-9A-F]{4}$")
SUB = re.compile(r"^([0-9A-F]{4})SUB([0-9A-F]+)$")


def read_eds(path: Path) -> configparser.ConfigParser:
    """The file as CiA 306 INI: duplicate sections or keys are errors (strict)."""
    parser = configparser.ConfigParser(strict=True, interpolation=None)
    parser.optionxform = str.lower
    parser.read_string(path.read_text(encoding="ascii"), str(path))
    return parser


def problems(path: Path) -> list[str]:
    """Every inconsistency of the EDS at `path`, named (empty: consistent)."""
    eds = read_eds(path)
    sections = {name.upper(): eds[name] for name in eds.sections()}
    found: list[str] = []
    info = sections.get("FILEINFO")
    if info is None or info.get("filename") != path.name:
        found.append(f"[FileInfo] FileName is not {path.name}")
    if info is None or info.get("edsversion") != "4.0":
        found.append("[FileInfo] EDSVersion is not 4.0")
    listed: dict[int, str] = {}
    for name in LISTS:
        section = sections.get(name.upper())
        if section is None:
            found.append(f"no [{name}]")
            continue
        count = int(section.get("supportedobjects", "-1"), 0)
        keys = {k for k in section if k != "supportedobjects"}
        if keys != {str(k) for k in range(1, count + 1)}:
            found.append(f"[{name}] SupportedObjects={count} but entries {sorted(keys)}")
        for key in sorted(keys):
            index = int(section[key], 0)
            if index in listed:
                found.append(f"0x{index:04X} in [{listed[index]}] and [{name}]")
            listed[index] = name
            manufacturer = 0x2000 <= index <= 0x5FFF
            if manufacturer != (name == "ManufacturerObjects"):
                found.append(f"0x{index:04X} listed in [{name}]")
    if not {0x1000, 0x1001, 0x1018} <= {i for i, n in listed.items() if n == "MandatoryObjects"}:
        found.append("[MandatoryObjects] lacks 0x1000, 0x1001 or 0x1018")
    objects = {int(name, 16) for name in sections if OBJECT.match(name)}
    for index in sorted(objects - set(listed)):
        found.append(f"[{index:04X}] is in no object list")
    for index in sorted(set(listed) - objects):
        found.append(f"0x{index:04X} is listed but has no section")
    subs: dict[int, set[int]] = {}
    for name in sections:
        match = SUB.match(name)
        if match:
            subs.setdefault(int(match[1], 16), set()).add(int(match[2], 16))
    for index in sorted(set(subs) - objects):
        found.append(f"sub-index sections of 0x{index:04X}, which has no section")
    for index in sorted(objects):
        found += _object_problems(sections, index, subs.get(index, set()))
    device = sections.get("DEVICEINFO")
    for key, low, high in (("nrofrxpdo", 0x1400, 0x15FF), ("nroftxpdo", 0x1800, 0x19FF)):
        count = sum(low <= i <= high for i in objects)
        if device is None or int(device.get(key, "-1"), 0) != count:
            found.append(f"[DeviceInfo] {key} is not {count}")
    pdos = [i for i in objects if 0x1400 <= i <= 0x15FF or 0x1800 <= i <= 0x19FF]
    for comm in sorted(pdos):
        if comm + 0x200 not in objects:
            found.append(f"PDO 0x{comm:04X} has no mapping object 0x{comm + 0x200:04X}")
    dummy = sections.get("DUMMYUSAGE")
    if dummy is None or {f"dummy000{k}" for k in range(1, 8)} - set(dummy):
        found.append("[DummyUsage] lacks Dummy0001..Dummy0007")
    return found


def _object_problems(sections: dict, index: int, subs: set[int]) -> list[str]:
    section = sections[f"{index:04X}"]
    kind = int(section.get("objecttype", "0x7"), 0)
    where = f"[{index:04X}]"
    if "parametername" not in section:
        return [f"{where} has no ParameterName"]
    if kind == VAR:
        return [f"{where}sub sections for a VAR"] * bool(subs) + _variable_problems(section, where)
    if kind not in (ARRAY, RECORD):
        return [f"{where} ObjectType 0x{kind:X}"]
    found = []
    count = int(section.get("subnumber", "-1"), 0)
    if count != len(subs):
        found.append(f"{where} SubNumber={count} but {len(subs)} sub-index sections")
    if 0 not in subs:
        return [*found, f"{where} has no sub0"]
    for sub in sorted(subs):
        found += _variable_problems(sections[f"{index:04X}SUB{sub:X}"], f"[{index:04X}sub{sub:X}]")
    sub0 = sections[f"{index:04X}SUB0"]
    mapping = 0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF  # sub0: entries mapped
    default = sub0.get("defaultvalue")
    if not mapping and default is not None and int(default, 0) != max(subs):
        found.append(f"{where}sub0 DefaultValue={default}, the highest sub-index is {max(subs)}")
    return found


def _variable_problems(section, where: str) -> list[str]:
    found = []
    for key in ("datatype", "accesstype", "pdomapping"):
        if key not in section:
            found.append(f"{where} has no {key}")
    if found:
        return found
    data_type = int(section["datatype"], 0)
    if data_type not in DATA_TYPES:
        found.append(f"{where} DataType 0x{data_type:04X}")
    if section["accesstype"].lower() not in ACCESS:
        found.append(f"{where} AccessType={section['accesstype']}")
    if section["pdomapping"] not in ("0", "1"):
        found.append(f"{where} PDOMapping={section['pdomapping']}")
    values = {k: section.get(k) for k in ("defaultvalue", "lowlimit", "highlimit")}
    numeric = data_type not in (0x0009, 0x000A, 0x000B, 0x000F)
    if numeric and all(v is None or "$" not in v.upper() for v in values.values()):
        default, low, high = (None if v in (None, "") else int(v, 0) for v in values.values())
        if default is not None and low is not None and default < low:
            found.append(f"{where} DefaultValue {default} below LowLimit {low}")
        if default is not None and high is not None and default > high:
            found.append(f"{where} DefaultValue {default} above HighLimit {high}")
    return found


@pytest.mark.parametrize("path", EDS_FILES, ids=lambda p: p.name)
def test_shipped_eds_files_are_consistent(path: Path) -> None:
    assert problems(path) == []
    eds = read_eds(path)
    sections = {name.upper() for name in eds.sections()}
    described = {int(name, 16) for name in sections if OBJECT.match(name)}
    # and the dummy entries [DummyUsage] allows, as data-type objects 0x0001-0x0007
    dummies = {k for k in range(1, 8) if eds.getint("DummyUsage", f"Dummy{k:04d}") == 1}
    assert set(canopen.import_od(str(path), 1)) == described | dummies  # canopen reads them


def test_the_checker_names_what_an_eds_checker_rejects(tmp_path: Path) -> None:
    """0x2000 listed as optional and manufacturer object (what main's EDS did), a
    missing section, a wrong count, a default outside its limits."""
    text = EDS_FILES[0].read_text()
    path = tmp_path / EDS_FILES[0].name
    broken = text.replace(
        "[ManufacturerObjects]\nSupportedObjects=0",
        (
            "[ManufacturerObjects]\nSupportedObjects=1\n1=0x2000\n\n"
            "[2000]\nParameterName=Vendor\nObjectType=0x7\nDataType=0x0005\nAccessType=rw\n"
            "DefaultValue=9\nLowLimit=0\nHighLimit=3\nPDOMapping=0"
        ),
    )
    broken = re.sub(
        r"(\[OptionalObjects\]\nSupportedObjects=)(\d+)",
        lambda m: m[1] + str(int(m[2]) + 1),
        broken,
    )
    count = int(re.search(r"\[OptionalObjects\]\nSupportedObjects=(\d+)", broken)[1])
    broken = broken.replace(f"\n{count - 1}=", f"\n{count}=0x2000\n{count - 1}=", 1)
    broken = broken.replace("[1017]", "[1017X]")
    path.write_text(broken)
    found = problems(path)
    assert "0x2000 in [OptionalObjects] and [ManufacturerObjects]" in found
    assert "0x2000 listed in [OptionalObjects]" in found
    assert "0x1017 is listed but has no section" in found
    assert "[2000] DefaultValue 9 above HighLimit 3" in found
