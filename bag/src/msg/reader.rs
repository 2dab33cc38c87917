//! Placeholder: primitive readers of CDR and ROS 1 serialization.
