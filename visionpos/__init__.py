"""visionpos: optical motion capture for indoor drone flight.

Pipeline stages live one per module; see docs/architecture.md.
"""

__version__ = "0.1.0"
