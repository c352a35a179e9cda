"""Identification toolkit: the seed papers' methods as pure fitting functions (CLI in `cli.py`).

- `thrust`: K(J) of the water-jet from thrust measurements (seed 000 sections 5-6).
- `free_decay`: spring and pendulum free decay, added mass, C_D, Chin K_L / K_Q (seed 001 sec. 3.2-3.3).
- `tables`: added mass vs depth per attitude and damping vs speed polynomials (seed 003 sec. 3.2).
- `azimuth`: pseudo-impulse design, signal compression and eq. 5 / 6 fits (seed 004 sec. 3-4).

Every fitting function takes arrays and returns a frozen dataclass; nothing here reads files.
"""
