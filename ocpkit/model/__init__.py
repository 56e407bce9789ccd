"""The model layer: a robot's dynamics (``dynamics``, ``rigid_body``, ``kinematics``), the input parameterization, task
terms and obstacles, the OCP that gathers them, and a problem (``problem``)."""
