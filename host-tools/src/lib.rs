//! Library behind the `host-tools` binary; one module per subcommand in [`cmd`].

// Every public item says what it is for (issue 24).
#![deny(missing_docs)]

pub mod calib;
pub mod cmd;
pub mod frames;
pub mod opencv_yaml;
pub mod placement;
