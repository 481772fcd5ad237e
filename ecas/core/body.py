"""The body every stage shares, defined once: SMPL-X's joints and expression coefficients, and MIBURI's regions.

Joint indices are SMPL-X's (gesture.body.skeleton.JOINT_NAMES). Each region is modelled by its own codec:
upper body + hands, lower body (with root velocity and foot contacts) and face (jaw + expressions).
"""

NUM_JOINTS = 55
NUM_EXPRESSIONS = 100

REGIONS = ("upper", "lower", "face")
UPPER_BODY_JOINTS = (3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21)
HAND_JOINTS = tuple(range(25, NUM_JOINTS))
UPPER_JOINTS = UPPER_BODY_JOINTS + HAND_JOINTS  # 43
LOWER_JOINTS = (0, 1, 2, 4, 5, 7, 8, 10, 11)
CONTACT_JOINTS = (7, 8, 10, 11)  # ankles and feet
JAW_JOINT = 22
PELVIS = 0
SPINE = (3, 6, 9)  # spine1-3, from the pelvis up to the chest (spine3)
HIPS = (1, 2)
KNEES = (4, 5)
ANKLES = (7, 8)
FEET = (10, 11)
NECK_HEAD = (12, 15)
COLLARS = (13, 14)
SHOULDERS = (16, 17)
ELBOWS = (18, 19)
WRISTS = (20, 21)
REGION_JOINTS = {"upper": UPPER_JOINTS, "lower": LOWER_JOINTS, "face": (JAW_JOINT,)}
