"""Network parts below both pipelines: the ImageNet-pretrained trunk that the robot parser
(perception/) and the cost-volume denoisers (method/designs/) both build on."""
