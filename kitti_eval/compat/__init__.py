"""Drop-ins for the evaluation functions of training frameworks: swap one import, keep the calling code.

* :mod:`kitti_eval.compat.openpcdet`: OpenPCDet's ``get_official_eval_result`` (also re-exported here and as
  ``kitti_eval.get_official_eval_result``)
* :mod:`kitti_eval.compat.mmdet3d`: mmdetection3d 1.x's ``kitti_eval`` and ``kitti_eval_coco_style``
"""

from __future__ import annotations

from .openpcdet import get_official_eval_result, ret_dict

__all__ = ["get_official_eval_result", "ret_dict"]
