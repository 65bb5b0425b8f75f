"""Reading inputs: OpenPCDet and mmdetection3d pickles (through the restricted unpickler), KITTI txt folders
and archives of them (one module per format in :mod:`kitti_eval.io.formats`), calibration."""
