"""The ROS 2 interface package ``ros2/rovergate_msgs`` (issue 29, part 2): built in a ROS 2
workspace, it gives ROS 2 nodes and tools rovergate's own message types. Its ``msg/`` files are
copies of ``rovergate/msg/`` (the definitions the wire and the bag use), its CMakeLists.txt
generates every one of them, and its package.xml depends on every package they use. No ROS is
installed here, so the files are read as colcon and rosidl would read them."""

from __future__ import annotations

import re
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "rovergate" / "msg"
PACKAGE = ROOT / "ros2" / "rovergate_msgs"
PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
              "int32", "uint32", "int64", "uint64", "string", "wstring"}


def _msgs(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.msg"))}


def _field_types(text: str) -> list[str]:
    """Each field's and constant's type, without its array or bound (``uint32[]`` ->
    ``uint32``, ``std_msgs/Header`` as it is)."""
    types = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            types.append(re.match(r"[A-Za-z0-9_/]+", line).group(0))
    return types


def _referenced_packages() -> set[str]:
    """The packages the .msg files use types of (``std_msgs/Header`` -> ``std_msgs``)."""
    own = {name.removesuffix(".msg") for name in _msgs(SOURCE)}
    packages = set()
    for name, data in _msgs(SOURCE).items():
        for t in _field_types(data.decode()):
            if "/" in t:
                packages.add(t.split("/")[0])
            else:  # rosidl: a bare name is a primitive or a message of this package
                assert t in PRIMITIVES or t in own, f"{name}: unknown type {t}"
    return packages


def test_the_msg_files_are_byte_identical_copies_of_rovergate_msg():
    source, copies = _msgs(SOURCE), _msgs(PACKAGE / "msg")
    assert source, "rovergate/msg/ holds no .msg file"
    assert sorted(copies) == sorted(source), "cp rovergate/msg/*.msg ros2/rovergate_msgs/msg/"
    stale = [name for name in source if copies[name] != source[name]]
    assert not stale, f"{stale} differ: cp rovergate/msg/*.msg ros2/rovergate_msgs/msg/"
    links = [p.name for p in (PACKAGE / "msg").iterdir() if p.is_symlink()]
    assert not links, f"{links} are symlinks: copy the files instead"


def test_cmakelists_generates_every_msg_with_its_dependencies():
    text = (PACKAGE / "CMakeLists.txt").read_text()
    assert re.search(r"^project\(rovergate_msgs\)", text, re.M)
    block = re.search(r"rosidl_generate_interfaces\(\$\{PROJECT_NAME\}(.*?)\)", text, re.S)
    assert block, "CMakeLists.txt has no rosidl_generate_interfaces(${PROJECT_NAME} ...)"
    listed, _, deps = block.group(1).partition("DEPENDENCIES")
    assert sorted(re.findall(r'"msg/([^"]+)"', listed)) == sorted(_msgs(SOURCE))
    assert set(deps.split()) == _referenced_packages()
    found = set(re.findall(r"^find_package\((\w+) REQUIRED\)", text, re.M))
    assert found >= {"ament_cmake", "rosidl_default_generators", *_referenced_packages()}
    assert "ament_package()" in text


def test_package_xml_is_an_interface_package_depending_on_what_the_msgs_use():
    root = ET.parse(PACKAGE / "package.xml").getroot()
    assert (root.tag, root.get("format")) == ("package", "3")

    def named(*tags: str) -> set[str]:
        return {e.text.strip() for tag in tags for e in root.findall(tag)}

    assert root.findtext("name") == "rovergate_msgs"
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert root.findtext("version") == version  # one release number for both
    assert "rosidl_default_generators" in named("buildtool_depend", "build_depend")
    assert "rosidl_default_runtime" in named("exec_depend")
    assert "rosidl_interface_packages" in named("member_of_group")
    assert root.findtext("export/build_type") == "ament_cmake"
    # Each package a .msg uses, at build time and at run time.
    build, run = named("depend", "build_depend"), named("depend", "exec_depend")
    missing = _referenced_packages() - (build & run)
    assert not missing, f"package.xml: add <depend>{'</depend>, <depend>'.join(missing)}</depend>"
