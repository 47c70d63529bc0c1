"""Maps that last: the map store (map.sqlite), live map queries, refitting a map to a corrected trajectory, and a
saved run's keyframes for the next session to register to."""
