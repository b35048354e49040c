"""What ``fusion-center report`` and ``fusion-center bandwidth`` compute and draw.

* :mod:`.bandwidth` - exact bus cost per cycle of raw-data vs decision streaming;
* :mod:`.build` - detection error against bus and CPU time for every rule (``report.json``);
* :mod:`.plots` - the report's figures (matplotlib, Agg);
* :mod:`.reference` - mpmath references of the threshold equations 16-18 (work-precision).
"""
