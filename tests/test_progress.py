"""Progress meters: what they print, at what rate, and that tqdm is imported only when used."""

import io
import re
import subprocess
import sys

import pytest

import cldyn


def test_text_meter_prints_rate_eta_and_info():
    stream = io.StringIO()
    meter = cldyn.TextProgressMeter(interval=0.0, file=stream)
    state = meter.start(100, initial=20, desc="fit")
    state = meter.update(state, 40, {"loss": 0.5, "validation": None})
    state = meter.update(state, 60, {"loss": 0.25})
    meter.close(state)
    lines = stream.getvalue().splitlines()
    assert lines[0] == "fit: 40/100 steps (40%) loss=0.5"  # no rate before a second update
    second = r"fit: 60/100 steps \(60%\), [0-9.e+]+ steps/s, ETA \d+:\d\d:\d\d loss=0.25"
    assert re.fullmatch(second, lines[1])
    assert re.fullmatch(r"fit: ended at 60/100 steps after \d+:\d\d:\d\d", lines[2])
    assert len(lines) == 3


def test_text_meter_is_rate_limited_but_keeps_the_first_and_last_line():
    stream = io.StringIO()
    meter = cldyn.TextProgressMeter(interval=3600.0, file=stream)
    state = meter.start(10, desc="record", unit="run")
    for done in range(1, 11):
        state = meter.update(state, done)
    meter.close(state)
    lines = stream.getvalue().splitlines()
    assert [line.split(" ")[1] for line in lines[:2]] == ["1/10", "10/10"]
    assert len(lines) == 3 and lines[2].startswith("record: ended at 10/10 runs")


def test_text_meter_close_flushes_an_unprinted_update_and_writes_to_stderr(capsys):
    meter = cldyn.TextProgressMeter(interval=3600.0)
    state = meter.start(10)
    state = meter.update(state, 2)
    state = meter.update(state, 5, {"loss": 1.5})
    meter.close(state)
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("2/10 steps") and err[1].startswith("5/10 steps") and "loss=1.5" in err[1]
    assert err[2].startswith("ended at 5/10 steps")
    with pytest.raises(ValueError, match="interval must be a finite number >= 0"):
        cldyn.TextProgressMeter(interval=-1.0)


def test_no_progress_meter_prints_nothing(capsys):
    meter = cldyn.NoProgressMeter()
    meter.close(meter.update(meter.start(5), 5, {"loss": 1.0}))
    assert capsys.readouterr() == ("", "")


def test_tqdm_meter_shows_progress_and_postfix():
    pytest.importorskip("tqdm")
    meter = cldyn.TqdmProgressMeter()
    state = meter.start(50, initial=10, desc="fit")
    state = meter.update(state, 30, {"loss": 0.125})
    assert state.n == 30 and state.total == 50 and "loss=0.125" in state.postfix
    meter.close(state)


def test_importing_cldyn_does_not_import_tqdm():
    code = "import sys, cldyn; print('tqdm' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"
