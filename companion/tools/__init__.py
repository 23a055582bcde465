"""Tools that evaluate and benchmark the companion (eval, bench, replay), apart from the runtime as
pytracking keeps its evaluation apart: they may import the runtime, the runtime never imports them."""
