"""What the sensor heads produce: scan patterns, the scanning and flash sensors, point clouds.

Above the models (``perception.targets``, ``config``, ``geometry``), below the estimators.
"""
