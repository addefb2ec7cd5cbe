"""Injection-recovery campaigns (``so-transients campaign CONFIG``): flares of known peak flux
and rise time injected into simulated noise-only observations, searched with the site config's
transient steps, matched to the truth, and summarized as the reference paper does (detection
thresholds, flux and pointing recovery, false positives). See :mod:`.run` for the layout of a
campaign folder and :mod:`.flare_injection` for the fast injection path.
"""
