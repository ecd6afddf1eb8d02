"""What logs say: spectra (`spectral`, LPSD), likelihoods of residuals (`whittle`), the plant
model driven by a log (`predict`), replay, the model-discrepancy workflow (`evidence`,
`diagnose`), gains suggested from the model (`suggest`), figures (`plots`) and synthetic logs
with a hidden effect (`synthetic`).

May import: the root vocabulary, settings and stand, `leveler.sim`, loop, log and the
virtual-run harness. Never daemon, emulate or cli."""
