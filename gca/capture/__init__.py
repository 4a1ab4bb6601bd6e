"""Your own object: a user's scan, camera and video as they come (see README, "Your own object").

- :mod:`gca.capture.objects`: the capture object kind of ``objects.<name>`` (a scan file of any name,
  optional mesh, cleaning/orientation/size options, density) and its import into the object frame;
- :mod:`gca.capture.cameras`: intrinsics + pose in OpenCV convention from COLMAP ``cameras.txt`` /
  ``images.txt`` and nerfstudio/Blender ``transforms.json`` (OpenGL axes converted);
- :mod:`gca.capture.spring_gaus`: the Spring-Gaus real-capture dataset's layout, one view for training.
"""
