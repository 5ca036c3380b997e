"""Recordings of a real rig (or simulated ones): ROS 2 bags and CSV pairs in
(eval.recording.bag), the simulated recording and its reference without the round trip
(eval.recording.simulate), the A-scan extraction in worker processes
(eval.recording.extraction), the fit of a recording: synchronisation, points, adaptive
and local-global model (eval.recording.fit), and its registration to an STL ground truth
(eval.recording.ground_truth)."""

# the scenes a recording is simulated in (eval.recording.simulate.RecordingSpec.scan)
SCANS = ("surgery", "phantom")
