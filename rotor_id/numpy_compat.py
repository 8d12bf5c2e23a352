"""
numpy functions under one name for both numpy lines this package runs on.

A stock ROS 2 Jazzy install (Ubuntu 24.04) has numpy 1.26; the pinned environment has numpy 2.
Where the two name a function differently, the library imports it from here.
"""

import numpy as np

#: ∫ y dx by the trapezoidal rule: ``np.trapezoid`` from numpy 2.0 on, ``np.trapz`` before
#: (numpy 2.4 removed that name).
trapezoid = getattr(np, 'trapezoid', None) or np.trapz
