"""Pure conversions between GauSem core types and standard ROS 2 messages. No nodes, no spinning."""
import gausem_core  # noqa: F401 (first: its OpenMP setting must precede torch's import)
from .camera_info import camera_info_to_camera, camera_to_camera_info
from .gaussian_map import (MAP_DTYPE, cloud_to_pointcloud2, cloud_to_points, pointcloud2_to_cloud,
                           transform_points)
from .images import (ImageEncodingError, depth_to_image, image_to_depth, image_to_labels, image_to_numpy,
                     image_to_rgb, labels_to_image, numpy_to_image, rgb_to_image)
from .loops import (information_to_sigmas, loop_candidate_to_record, loop_constraint_to_record,
                    place_signature_to_record, pose_graph_update_from_core, pose_graph_update_to_core,
                    record_to_loop_candidate, record_to_loop_constraint, record_to_place_signature,
                    sigmas_to_information)
from .occupancy import grid_to_occupancy_grid, occupancy_grid_to_cells
from .poses import (matrix_to_odometry, matrix_to_pose, matrix_to_pose_stamped, matrix_to_transform,
                    odometry_to_matrix, path_to_poses, pose_stamped_to_matrix, pose_to_matrix, poses_to_path,
                    transform_to_matrix)
from .records import (KeyframeRecord, LoopCandidateRecord, LoopConstraintRecord, PlaceSignatureRecord, PoseGraphNode,
                      PoseGraphNodeKind, PoseGraphUpdate, SubmapEvent, SubmapEventKind,
                      pointcloud2_to_pose_graph_update, pointcloud2_to_records, pose_graph_update_to_pointcloud2,
                      records_to_pointcloud2)
from .stamps import (header_seconds, make_header, ns_to_seconds, ns_to_time, seconds_to_ns, seconds_to_time,
                     time_to_ns, time_to_seconds)
