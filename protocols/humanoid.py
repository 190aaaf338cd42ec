"""The standard humanoid: the bones engines expect (Unity HumanBodyBones without eyes,
jaw and fingers; what VMC receivers animate), parents first, with their parents.

One definition for the rig mapping, the retargeting target and the VMC encoder.
"""

from __future__ import annotations

#: Parent of each standard humanoid bone (None for Hips), parents before children.
HUMANOID_PARENTS: dict[str, str | None] = {
    "Hips": None,
    "Spine": "Hips",
    "Chest": "Spine",
    "UpperChest": "Chest",
    "Neck": "UpperChest",
    "Head": "Neck",
    "LeftShoulder": "UpperChest",
    "LeftUpperArm": "LeftShoulder",
    "LeftLowerArm": "LeftUpperArm",
    "LeftHand": "LeftLowerArm",
    "RightShoulder": "UpperChest",
    "RightUpperArm": "RightShoulder",
    "RightLowerArm": "RightUpperArm",
    "RightHand": "RightLowerArm",
    "LeftUpperLeg": "Hips",
    "LeftLowerLeg": "LeftUpperLeg",
    "LeftFoot": "LeftLowerLeg",
    "LeftToes": "LeftFoot",
    "RightUpperLeg": "Hips",
    "RightLowerLeg": "RightUpperLeg",
    "RightFoot": "RightLowerLeg",
    "RightToes": "RightFoot",
}

#: The 22 standard humanoid bones, parents first.
HUMANOID_BONES: tuple[str, ...] = tuple(HUMANOID_PARENTS)
