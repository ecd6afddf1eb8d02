"""config/phoebus/leveler.bob, the Phoebus / CS-Studio display, held to the PVs the daemon
serves: a renamed or new PV that the panel does not follow fails here, not in the lab."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest
from conftest import REPO

pytest.importorskip("caproto", reason="caproto (the epics extra) is not installed")

from leveler.live.epics_ioc import _groups

DISPLAY = REPO / "config" / "phoebus" / "leveler.bob"


def served(writable: bool) -> set[str]:
    readable, writable_group = _groups()
    return set(((writable_group if writable else readable)(prefix="LEV:")).pvdb)


def display_pvs() -> dict[str, set[str]]:
    """Each PV the display names, by where it is named (widget pv_name, trace, action)."""
    root = ET.parse(DISPLAY).getroot()
    assert root.tag == "display" and root.get("version") == "2.0.0"
    assert root.findtext("macros/P") == "LEV:"  # the [epics] default prefix
    found: dict[str, set[str]] = {"widget": set(), "trace": set(), "write": set()}
    for w in root.iter("widget"):
        if (pv := w.findtext("pv_name")) is not None:
            found["widget"].add(pv)
        found["trace"] |= {t.text or "" for t in w.iter("y_pv")}
        found["write"] |= {a.findtext("pv_name") or "" for a in w.iter("action")
                           if a.get("type") == "write_pv"}
    return {k: {v.replace("$(P)", "LEV:") for v in vs} for k, vs in found.items()}


def test_every_pv_the_display_names_is_served_and_every_served_pv_is_shown() -> None:
    named = display_pvs()
    everything = set().union(*named.values())
    assert everything <= served(writable=True), everything - served(writable=True)
    assert served(writable=False) <= named["widget"], served(writable=False) - named["widget"]
    assert served(writable=True) <= everything  # the controls too
    assert named["trace"] == {"LEV:READING", "LEV:TILT"}


def test_its_buttons_write_what_the_switches_accept() -> None:
    root = ET.parse(DISPLAY).getroot()
    writes = {(a.findtext("pv_name"), a.findtext("value")) for a in root.iter("action")
              if a.get("type") == "write_pv"}
    assert writes == {("$(P)ENGAGE", "1"), ("$(P)ENGAGE", "0"), ("$(P)RESET", "1")}
