"""The evaluation itself: the KITTI rules as data, boxes, overlaps, matching, curves and AP, results."""
