"""Labels and training data: the web labeller, two labellings compared, and the simulator's
training data exported as COCO or YOLO."""
