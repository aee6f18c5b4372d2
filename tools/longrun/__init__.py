"""``python -m tools.longrun``: the live node fed one bag over and over, for hours.

``parproj_node`` runs in its own process (reliable input QoS, as in the demo). The bag
(default ``bags/ikonos_agile``) is published again and again; repetition ``k`` has every header
stamp and log time moved forward by ``k`` times (bag duration + ``margin_s``), and its scene ids
(the strips' ``header.frame_id``, the scene ids of the GCP observations) and GCP ids prefixed
with ``r<k>_``, so that each repetition is a new acquisition to the node. Messages go out as fast
as the node acknowledges them (rate 0) unless a rate is given; a repetition is sent only when
the pairs of the repetition ``in_flight`` before it have come back, so the replay runs at the
rate the node sustains instead of filling its input queue. A repetition's latched inputs (GCP,
scanner info, truth points) are sent, and acknowledged, before its stream of navigation and
strips, as a ground station latches them ahead of a pass.

While it runs, the node's resident memory (``/proc/<pid>/status`` VmRSS) is sampled every second (a
thread of this process), its 1 Hz ``/diagnostics`` summary (counters, input queue length and peak,
navigation samples and GCP held) is recorded, and every pair that comes back is checked
(:class:`~tools.longrun.checks.PairChecker`): StereoPair with its left, right and anaglyph images
(or its column blocks), finite transforms, image sizes equal to the StereoPair's width and height,
scene ids of one repetition, and every number of the pair (both scenes' parameters, the
normalization, grids, y-parallax statistics), the images and the y-parallax of the bag's truth
points equal to the first repetition's.

The tolerance of that last comparison is zero (bit for bit), by design: the pipeline sees a
repetition only through differences of integer-nanosecond stamps, which are exact, through the
same pixels and the same GCP, and it is deterministic (tie-point RANSAC seeded, SIFT and the
brute-force matcher deterministic). Any difference is a defect: absolute time leaking into
floating point (a float64 of 1.7e9 s has a 2.4e-7 s step, 1.5e-3 lines at 6500 lines/s), or
state carried over from one acquisition to the next.

The report (``longrun.json``, ``longrun.png`` with RSS and queue against time, a printed table):
wall and simulated duration, repetitions, pairs expected / published / malformed, drops
(``strips_rejected``, ``nav_rejected``, messages sent but not received by the node, warnings
and errors on ``/diagnostics``), RSS start / end / max and its slope (least squares after a
warm-up) in MB per hour and per pair, and that of the per-minute medians over the second half
(robust to spikes and to a late allocator step), and the queue length.

Modules: ``checks`` (the repetitions of the bag and the checks of the pairs), ``run`` (the run,
its report and plot, its command line). ``bench/``'s harness: :mod:`tools.harness`.
"""
