"""The simulator: worlds with ground truth, vehicles, sensors and a camera renderer, writing drive
logs (common/drivelog.py).

worlds.py (load_world, repaint) <- town.py | lanelet2.py (+ osm.py) | av2.py, built from paint.py
geometry and routes.py helpers; simulate.py (simulate_drives) drives motion.py trajectories
through sensors.py noise models and render.py (labels via raster.py tiles, RGB); comma2k19.py
converts a real drive; cli.py backs `roadmap sim` and `roadmap world render`."""
