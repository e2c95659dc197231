"""A virtual intercomparison (key comparison) of road-surface goniophotometers (issue 20).

Rooms: :mod:`.statistics` (the comparison's statistics, pure numpy).
"""
