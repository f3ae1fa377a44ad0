"""Same-observation, same-noise replay (paper `sec:lattice`, App. `app:pi05_replay`).

    record.py         full-precision trajectories in the simulator: observations, RNG state per call,
                      normalized chunks, flow states, executed actions (`records.json` + npz)
    configuration.py  one configuration replayed on them through `quantize_` (checked layer count)
    run.py            a replay's output on disk (`<config>.json` + `<config>.npz`)
    composition.py    the statistics as pure array functions
    analysis.py       one format's replays -> `analysis.json` (the authors' layout)
    study.py, tables.py, figure.py   study definition (`studies/*.yaml`), tables and figure
"""
