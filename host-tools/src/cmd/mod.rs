//! One module per subcommand; each has `Args` (clap) and `run`.

pub mod simulate;
pub mod track;
pub mod plan;
pub mod accuracy;
pub mod calibrate;
pub mod push_params;
pub mod show_params;
pub mod convert_params;
pub mod robot_sim;
pub mod record;
pub mod path;
pub mod register;
pub mod keygen;
pub mod measure_tool;
