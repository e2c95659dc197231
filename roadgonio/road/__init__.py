"""From the r-table to the road: EN 13201-3 luminance metrics of a luminaire layout computed with a
measured or corrected r-table, with its uncertainty (issue 13)."""
