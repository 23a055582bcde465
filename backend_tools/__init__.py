"""Tools that evaluate and benchmark the back-end (detect, eval, bench, capacity, detector recall, int8
quantisation, the verifier table, the WordNet table's generator, the VLM emulator and the loopback service
harnesses), apart from the service as `companion_tools/` is from the companion: they may import the
service; `cloudtrack-backend` finds their subcommands through the `cloudtrack.backend_commands` entry
points and never imports them."""
