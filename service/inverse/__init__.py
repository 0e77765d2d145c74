"""Inverse transform: frames -> shape coefficients (d, p, a, b) and centre displacement D(0, t).

The per-frame methods (:mod:`.network`, :mod:`.nearest`) behind one interface (:mod:`.base`), opened by name
(:mod:`.methods`), and the window-level methods on top of them (:mod:`.regularised`, :mod:`.synthesis`).
Nothing is imported here, so that naming the methods (``--help``) loads none of them."""
