"""``python -m tools.bench``: speed and memory of the normalization against its lower bounds.

Five parts, each on synthetic IKONOS-like data (c = 10 m, 12 um pixels, 6500 lines/s, uint16):

1. Resampling micro-benchmark on one scene (``lines`` x ``detectors``) and an output grid of the
   same size: :func:`~parproj_ros.imaging.resample.resample` (bilinear) against
   ``cv2.warpAffine`` with the affine part of the map only (the lower bound of the operation),
   ``scipy.ndimage.map_coordinates(order=1)`` on the exact map (what a plain Python
   implementation does; timed on a band of rows and scaled) and ``np.copyto`` of the output
   (memory bandwidth). Figures are output megapixels per second; ratios are times relative to
   ``warpAffine``. The geometric error of ``resample`` is measured against the exact map with
   float32 sources whose values are their own sample and line coordinates.
2. End to end over DDS: strips of fore/aft scenes published at 6500 lines/s per view into
   ``parproj_node`` (its own process) on this machine; real-time factor, latency from a pair's
   last strip to its StereoPair, strips dropped, and the node's resident memory over the run;
   and, first, the same strips into a subscriber that only counts them (the DDS ceiling).
3. Offline: the same data written to a bag and run through ``process_bag`` (``parproj
   process``), with a cProfile breakdown of where the time goes.
4. Scaling: ``resample`` and ``warpAffine`` times over scene lengths and widths.

The platform: a satellite at 680 km, roll -5 deg, flying along X at the speed that makes 6500
lines/s give square pixels (5304 m/s; IKONOS slows its scan by pitching back to get them), with
fore and aft cameras pitched -+theta. theta is chosen so that the aft camera images the fore
camera's ground one scene later: scene k of the aft view is exposed while scene k+1 of the fore
view is, interleaved strip by strip as a real fore/aft sensor delivers them, and pair k completes
with the aft scene k. A larger stereo angle only delays the aft stream further and makes the node
hold more fore scenes. Every scene has the same random 11-bit content (one block per strip
position), so the pair is photometrically consistent; rendering through a terrain is too slow
at this size.

``python -m tools.bench [--quick] [--json]`` runs it (:mod:`tools.bench.run`); ``bench/run.sh``
runs the quick and the full benchmark and rewrites ``bench/BENCHMARKS.md``. Modules: ``config``
(sizes), ``micro`` (parts 1 and 4), ``dds`` (part 2), ``offline`` (part 3), ``report`` (summary,
targets, tables), ``run`` (the whole run and its command line). The synthetic platform and
acquisition are :mod:`parproj_ros.sim.synthetic` (the streaming tests use them too).
"""
