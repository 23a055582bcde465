"""The ground side of the link: `cloudtrack-gcs` and the MAVProxy module. It shares the wire protocol
with the companion through `cloudtrack` and never imports `companion`."""
