import sys, numpy as np, torch
from avatarctl.project import Project
from avatarctl.io.project_io import load_project_capture
from avatarctl.body.anny_model import AnnyBody
cap = load_project_capture(Project.open(sys.argv[1]))
b = AnnyBody(); t = b.template(cap.motion); p = b.pose(cap.motion)
np.savez_compressed(sys.argv[2], name="anny", vertices=t.vertices.numpy(), faces=t.faces.numpy(),
    skin_weights=t.skin_weights.numpy().astype(np.float16), parents=np.array(t.parents), joint_names=np.array(t.joint_names),
    pose_parameters=np.asarray(cap.motion.pose_parameters, dtype=np.float32), joint_transforms=p.joint_transforms.numpy(),
    posed_vertices=p.vertices.numpy().astype(np.float16), pose_features=p.pose_features.numpy())
