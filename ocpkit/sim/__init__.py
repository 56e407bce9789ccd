"""The closed loop and its pictures: ``simulate``, MuJoCo as the plant, metrics, figures and animations."""
