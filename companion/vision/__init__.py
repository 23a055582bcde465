"""Vision on the companion: frame sources, trackers, loss detection, latency compensation and the
tracking front-end that turns each frame into a `TrackResult`. No MAVLink, no back-end."""
