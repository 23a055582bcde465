"""The companion's side of the back-end: the detect worker (one keyframe in flight), the session
(status reports, supervisor decisions) and the candidate crop the status carries."""
