"""scripts/bench_defaults.py's table cells: loop closure's counts where it ran, none where it did not."""


def test_a_cell_counts_loops_where_loop_closure_ran(script):
    cell = script("bench_defaults").cell
    off = {"ate_rmse_m": 0.0273, "ate_percent_of_path": 0.69, "untracked_frames": 0, "keyframes": 0,
           "loops_applied": 0, "frames_with_second_start": 0}
    assert cell(off) == "2.73 cm (0.69 %), 0 lost, 2nd start on 0"
    on = dict(off, keyframes=19, loops_applied=0)
    assert cell(on) == "2.73 cm (0.69 %), 0 lost, 0 loops, 2nd start on 0"
    refused = dict(on, loops_applied=15, loops_refused=[{"from": 0, "to": 82, "why": "outlier"}] * 25)
    assert cell(refused) == "2.73 cm (0.69 %), 0 lost, 15 loops (25 refused), 2nd start on 0"
    assert cell(None) == "failed"
