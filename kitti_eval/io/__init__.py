"""Reading inputs: OpenPCDet and mmdetection3d pickles (through the restricted unpickler), KITTI txt folders
and archives of them, calibration; and the synthetic KITTI generator behind the demo data."""
