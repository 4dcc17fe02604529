"""Applications that compose the whole system (core, bridge, stations): the demo, the served fusion service.

The application layer: the core never imports it (tests/test_layers.py).
"""
