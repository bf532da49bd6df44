//! Library behind the `host-tools` binary; one module per subcommand in [`cmd`].

pub mod calib;
pub mod cmd;
pub mod frames;
pub mod opencv_yaml;
