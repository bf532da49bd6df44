//! One module per subcommand; each has `Args` (clap) and `run`.

pub mod accuracy;
pub mod calibrate;
pub mod capture;
pub mod cluster_keys;
pub mod convert_params;
pub mod keygen;
pub mod measure_tool;
pub mod path;
pub mod pivot;
pub mod plan;
pub mod push_params;
pub mod record;
pub mod register;
pub mod robot_sim;
pub mod show_params;
pub mod simulate;
pub mod survey;
pub mod track;
pub mod update;
pub mod wand_calibrate;
