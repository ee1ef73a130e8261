"""Input decisions: close calls are told apart from clear ones, and lower an ``ok`` verdict to ``check``."""

from dsareg_engine.io.input_decisions import InputDecision, with_close_calls


def _result(verdict: str) -> dict:
    return {"verdict": verdict, "metrics": {"confidence": {"verdict": verdict, "reasons": [], "signals": {}}}}


def test_a_measure_inside_the_band_is_a_close_call_and_outside_is_not():
    near = InputDecision("ap", "run kind", "native", "contrast ratio", measure=4.3, threshold=4.0, band=0.5)
    far = InputDecision("ap", "run kind", "native", "contrast ratio", measure=6.0, threshold=4.0, band=0.5)
    assert near.close and abs(near.margin - 0.3) < 1e-12
    assert not far.close
    given = InputDecision("mesh", "units", "m", "option", source="option")
    assert not given.close and given.margin is None


def test_a_close_call_lowers_ok_to_check_with_its_reason():
    near = InputDecision("lat", "run kind", "subtracted", "contrast ratio", measure=3.9, threshold=4.0, band=0.5)
    data = with_close_calls(_result("ok"), [near])
    assert data["verdict"] == "check" and data["metrics"]["confidence"]["verdict"] == "check"
    assert any("lat: run kind read as subtracted on a close call" in r for r in data["metrics"]["confidence"]["reasons"])
    assert data["input_decisions"][0]["close"] is True


def test_failed_stays_failed_and_clear_decisions_change_nothing():
    near = InputDecision("volume", "volume kind", "cta", "HU", measure=1.0, threshold=1.1, band=0.5)
    assert with_close_calls(_result("failed"), [near])["verdict"] == "failed"
    far = InputDecision("volume", "volume kind", "cta", "HU", measure=9.0, threshold=1.1, band=0.5)
    data = with_close_calls(_result("ok"), [far])
    assert data["verdict"] == "ok" and data["metrics"]["confidence"]["reasons"] == []
    assert with_close_calls(_result("ok"), []) == _result("ok")


def test_a_close_call_no_option_states_asks_for_a_check_only():
    optionless = InputDecision("volume", "venous sinuses", "1 set aside", "share along bone", measure=0.75,
                               threshold=0.7, band=0.15)
    assert optionless.reason().endswith("check that this is right")
    stated = InputDecision("volume", "vessel window", "180 and up HU", "contrast", measure=110.0, threshold=100.0,
                           band=50.0)
    assert stated.reason().endswith("or state it in the options")
