"""Hostile inputs (malformed files, bad scenarios, unsafe artefacts, escaping paths): each is refused with an error
naming file and field, or cleaned up as documented. The cases are defined once in r1sim_sumo.reliability.cases
(the reliability report runs the same table)."""

from __future__ import annotations

import pytest

from r1sim_sumo.reliability.cases import cases, run_case

_CASES = cases()


@pytest.mark.parametrize("case", [pytest.param(c, id=c.name, marks=[getattr(pytest.mark, m) for m in c.marks]) for c in _CASES])
def test_hostile_input(case, tmp_path):
    out = run_case(case, tmp_path / case.name)
    assert out.passed, f"{case.name} ({case.description}): {out.message}"
    if case.expect is not None:  # the error names what the case promised (file, field)
        assert all(m in out.message for m in case.match)


def test_case_table_covers_every_category():
    cats = {c.category for c in _CASES}
    assert {"SUMO network", "SUMO config / routes", "scenario", "dataset", "logged CSV", "highD", "config", "artefact", "paths"} <= cats
    assert len({c.name for c in _CASES}) == len(_CASES)  # unique names (report rows)


def test_safe_join_accepts_plain_names(tmp_path):
    from r1sim_sumo.safe_paths import UnsafePathError, safe_join, safe_name

    assert safe_join(tmp_path, "a/b.npz") == tmp_path / "a" / "b.npz"
    assert safe_join(tmp_path, "states/net__seed00001/w00010.state.xml.gz").parent.name == "net__seed00001"
    (tmp_path / "inner").mkdir()
    (tmp_path / "alias").symlink_to(tmp_path / "inner", target_is_directory=True)
    assert safe_join(tmp_path, "alias/x.txt") == tmp_path / "alias" / "x.txt"  # a symlink staying inside is fine
    for bad in ("", "a/../../b", "..", "C:\\x", "\\\\server\\share", "a\x00b"):
        with pytest.raises(UnsafePathError):
            safe_join(tmp_path, bad)
    assert safe_name("motorway_merge__seed00001") == "motorway_merge__seed00001"
    for bad in ("..", ".", "a/b", ""):
        with pytest.raises(UnsafePathError):
            safe_name(bad)
