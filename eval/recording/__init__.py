"""Recordings of a real rig (or simulated ones): ROS 2 bags and CSV pairs in
(eval.recording.bag), the simulated recording (eval.recording.simulate), and the fit of a
recording: synchronisation, points, adaptive model, registration to an STL ground truth
(eval.recording.fit)."""
