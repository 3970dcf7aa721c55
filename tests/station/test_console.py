"""Issue 15: a console that reads at a glance, and the shift summary behind it."""

from __future__ import annotations

import numpy as np

from sofast_station.station import console
from sofast_station.result.faults import fault_kind
from sofast_station.result.shift import summarize


def _rec(serial, verdict, fx=None, fy=None, design=None, parab=None, reasons=(), cycle=None, **extra):
    rec = {"serial": serial, "verdict": verdict, "reasons": list(reasons), "cycle_id": "20261201T101010123-0a1b2c3d"}
    if fx is not None:
        rec.update(focal_length_x_m=fx, focal_length_y_m=fy, twist_mrad_per_m=0.1,
                   slope_rms_mrad={"design": {"magnitude": design}, "parabola": {"magnitude": parab}})
    if cycle is not None:
        rec["timings_s"] = {"until_journal": cycle}
    rec.update(extra)
    return rec


ROWS = [
    (_rec("SIM-0001", "pass", 5.4183, 5.3512, 0.61, 0.52), "pass"),
    (_rec("F-2", "fail", 5.6001, 5.1, 3.4, 2.5, reasons=["focal length x 5.6001 m is +5.07 % from design",
                                                          "design slope error 3.400 mrad RMS (limit 3)"]), "fail"),
    (_rec("SIM-0003", "invalid", 5.41, 5.35, 0.6, 0.5, reasons=["fringe contrast too low"]), "invalid"),
    (_rec("SIM-0004", "fault", reasons=["camera: no frame within 2 s"]), "fault"),
    (_rec("A-VERY-LONG-SERIAL-NUMBER-0000000005", "pass", 5.4183, 5.3512, 0.61, 0.52,
          focal_length_x_m_U=0.0021, focal_length_y_m_U=0.0019,
          slope_rms_mrad_U={"design": {"magnitude": 0.03}, "parabola": {"magnitude": 0.02}}), "pass"),
]


def _column_starts(line: str) -> list[int]:
    """Where each run of non-blanks that follows two blanks starts (the column boundaries)."""
    return [i for i in range(2, len(line)) if line[i] != " " and line[i - 2:i] == "  "]


def test_every_kind_of_row_lines_up_with_the_header():
    head = console.header(total=20)
    lines = [console.facet_line(rec, answer, 0.53 + i, n=i + 1, total=20) for i, (rec, answer) in enumerate(ROWS)]
    # the verdict column starts at the same place on every row and under its heading
    v = head.index("verdict")
    for line, (_, answer) in zip(lines, ROWS):
        assert line[v:v + len(answer)] == answer.upper(), (head, line)
    # the cycle time ends at the same column as its heading on every row
    c_end = head.index("cycle") + len("cycle")
    for line in lines:
        assert line[c_end - 1] == "s" and line[c_end - 6:c_end - 1].strip().replace(".", "").isdigit(), (head, line)
    # the figures sit right-aligned under their headings (a dash when missing)
    f_end = head.index("f_x (m)") + len("f_x (m)") - console._FIGURES[0][3]   # the value ends before its "± U" room
    assert lines[0][f_end - 6:f_end] == "5.4183" and lines[3][f_end - 1] == "-"
    assert "".join(ch for ch in lines[3][head.index("verdict") + 7:c_end - 7] if ch not in " -") == ""


def test_count_uncertainty_long_serial_and_every_reason():
    lines = [console.facet_line(rec, answer, 1.0, n=i + 1, total=20) for i, (rec, answer) in enumerate(ROWS)]
    assert lines[0].lstrip().startswith("1/20 ")
    assert lines[1].endswith("focal length x 5.6001 m is +5.07 % from design; design slope error 3.400 mrad RMS "
                             "(limit 3)")
    assert "camera: no frame within 2 s" in lines[3]
    assert "5.4183 ± 0.0021" in lines[4] and "0.610 ± 0.030" in lines[4]   # GUM: U to two digits
    assert "A-VERY-LONG-SER…" in lines[4] and len(lines[4]) >= len(lines[0])
    assert console.facet_line(ROWS[0][0], "pass", 1.0, n=7).lstrip().startswith("7 ")   # N unknown: n alone
    # the log line names every reason and the cycle
    log = console.log_line(ROWS[1][0], "fail", 1.25, n=2, total=20)
    assert log.startswith("facet 2/20 serial='F-2'") and "cycle_s=1.250" in log
    assert "+5.07 % from design | design slope error" in log


def test_shift_summary_yield_spread_and_cycle_times():
    rng = np.random.default_rng(4)
    fx = 5.42 + 0.002 * rng.standard_normal(30)
    times = 0.5 + rng.random(33)
    records = [_rec(f"S{i}", "pass", fx[i], 5.35, 0.6, 0.5, cycle=times[i]) for i in range(30)]
    records += [_rec("F1", "fail", 5.9, 5.35, 0.6, 0.5, reasons=["focal length x"], cycle=times[30]),
                _rec("X1", "fault", reasons=["camera: lost"], cycle=times[31]),
                _rec("X2", "fault", reasons=["timeout: no result within 10 s"], cycle=times[32])]
    s = summarize(records)
    assert s.total == 33 and s.counts == {"pass": 30, "fail": 1, "indeterminate": 0, "invalid": 0, "fault": 2}
    # the two faults (a camera, a timeout) are the station's, not the facets': out of the yield
    assert s.yield_fraction == 30 / 31 and s.station_faults == 2
    all_fx = np.append(fx, 5.9)
    st = s.figures["focal_length_x_m"]
    assert st.n == 31 and np.isclose(st.mean, all_fx.mean()) and np.isclose(st.std, all_fx.std(ddof=1))
    assert np.isclose(s.cycle_median_s, np.median(times)) and np.isclose(s.cycle_p95_s, np.percentile(times, 95))
    assert s.cycle_worst_s == times.max()
    assert s.faults_by_kind == {"camera": 1, "timeout": 1}
    text = console.summary_text(s)
    assert "yield 96.8 % (30/31) (2 fault(s) of the station not counted" in text and "2 fault" in text
    assert f"{all_fx.mean():.4f}" in text and f"{all_fx.std(ddof=1):.4f}" in text
    assert f"median {np.median(times):.2f} s, 95th percentile {np.percentile(times, 95):.2f} s" in text
    assert fault_kind({"reasons": ["some free text without a kind"]}) == "other"


def test_running_tally_matches_the_list_summary_and_keeps_a_fixed_size():
    """The run's summary is running statistics: the same figures as summarising every record, in memory
    that does not grow with the number of facets (a station runs for months)."""
    import pickle

    from sofast_station.result.shift import ShiftTally

    rng = np.random.default_rng(7)
    records = []
    for i in range(400):
        verdict = ("pass", "pass", "pass", "fail", "fault")[i % 5]
        fx, fy = 5.42 + 0.003 * rng.standard_normal(), 5.35 + 0.002 * rng.standard_normal()
        records.append(_rec(f"S{i}", verdict, fx, fy, 0.6, 0.5, reasons=["camera: lost"] if verdict == "fault" else [],
                            cycle=0.5 + rng.random()))
    tally = ShiftTally(cycle_window=50)
    sizes = []
    for i, rec in enumerate(records):
        tally.add(rec)
        if i + 1 in (100, 400):
            sizes.append(len(pickle.dumps(tally)))
    full, running = summarize(records), tally.summary()
    assert running.counts == full.counts and running.total == 400 and running.faults_by_kind == {"camera": 80}
    for path, st in full.figures.items():
        assert running.figures[path].n == st.n
        assert np.isclose(running.figures[path].mean, st.mean, rtol=1e-12)
        assert np.isclose(running.figures[path].std, st.std, rtol=1e-9)
    assert running.cycle_worst_s == full.cycle_worst_s
    last = [r["timings_s"]["until_journal"] for r in records[-50:]]
    assert np.isclose(running.cycle_median_s, np.median(last))
    assert sizes[1] - sizes[0] < 32, sizes          # 300 more facets: a few bytes (counts), not a row each
