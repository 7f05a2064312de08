//! The command line as a user meets it, run as a process: colours and `NO_COLOR`, shell
//! completions and manual pages, a reader that goes away (`| head -1`), what `rectify`
//! says it wrote, and error messages that name the cause once with the remedy.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use sdsem::testing::{Texture, dome, render};
use sdsem::vision::Image;

const ESC: &str = "\u{1b}[";

fn sdsem() -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_sdsem"));
    cmd.current_dir(env!("CARGO_MANIFEST_DIR"))
        .env_remove("NO_COLOR")
        .env_remove("CLICOLOR")
        .env_remove("CLICOLOR_FORCE")
        .env_remove("RUST_LOG");
    cmd
}

fn run(cmd: &mut Command) -> Output {
    cmd.stdin(Stdio::null()).output().unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// A 256×192 dome pair with a horizontal parallax (tilt axis φ = −90°), as PNGs in `dir`.
fn dome_pair(dir: &Path) -> (PathBuf, PathBuf) {
    let (w, h) = (256, 192);
    let pair = render(
        w,
        h,
        Texture::new(5),
        &dome(w, h, 0.0, 6.0, 0.35),
        0.0,
        0.005,
    );
    let save = |name: &str, img: &Image| {
        let path = dir.join(name);
        image::GrayImage::from_raw(w as u32, h as u32, img.to_u8())
            .unwrap()
            .save(&path)
            .unwrap();
        path
    };
    (save("left.png", &pair.left), save("right.png", &pair.right))
}

#[test]
fn help_has_examples_and_no_color_turns_its_colours_off() {
    let coloured = run(sdsem()
        .args(["reconstruct", "--help"])
        .env("CLICOLOR_FORCE", "1"));
    assert!(coloured.status.success());
    let help = text(&coloured.stdout);
    assert!(help.contains(ESC), "CLICOLOR_FORCE shows colours:\n{help}");
    assert!(help.contains("Examples:"), "{help}");
    assert!(!help.contains("series."), "{help}");

    let plain = run(sdsem()
        .args(["reconstruct", "--help"])
        .env("CLICOLOR_FORCE", "1")
        .env("NO_COLOR", "1"));
    let help = text(&plain.stdout);
    assert!(
        !help.contains(ESC),
        "NO_COLOR beats CLICOLOR_FORCE:\n{help}"
    );
    assert!(help.contains("Examples:\n  sdsem reconstruct left.tif right.tif --out out"));
}

/// A minimal acquisition on the built-in simulator (one step, small frames, no
/// reconstruction): it logs at INFO, which is what the colour test needs.
fn tiny_run(dir: &Path) -> Command {
    let mut cmd = sdsem();
    cmd.args([
        "--log-format",
        "text",
        "acquire",
        "--config",
        "config/sim.toml",
    ])
    .args(
        [
            format!("run.output_dir={}", dir.display()),
            "run.reconstruct=false".into(),
            "series.end_tilt_deg=1".into(),
            "imaging.micrograph.width=160".into(),
            "imaging.micrograph.height=120".into(),
            "imaging.tracking.width=160".into(),
            "imaging.tracking.height=120".into(),
            "simulator.time_scale=0.01".into(),
        ]
        .iter()
        .flat_map(|s| ["--set".to_owned(), s.clone()]),
    );
    cmd
}

#[test]
fn logs_are_coloured_only_without_no_color() {
    let dir = tempfile::tempdir().unwrap();
    let coloured = run(tiny_run(dir.path()).env("CLICOLOR_FORCE", "1"));
    let log = text(&coloured.stderr);
    assert!(coloured.status.success(), "{log}");
    assert!(log.contains("run started") && log.contains(ESC), "{log}");

    let plain = run(tiny_run(dir.path())
        .env("CLICOLOR_FORCE", "1")
        .env("NO_COLOR", "1"));
    let log = text(&plain.stderr);
    assert!(plain.status.success(), "{log}");
    assert!(log.contains("run started"), "{log}");
    assert!(!log.contains(ESC), "NO_COLOR: no escape codes in\n{log}");
    // The re-centring lines carry their figures rounded to 1 nm.
    assert!(
        !log.contains("0000000"),
        "unrounded figures in the log:\n{log}"
    );
}

#[test]
fn completions_are_generated_for_every_shell() {
    for (shell, marker) in [
        ("bash", "_sdsem()"),
        ("zsh", "#compdef sdsem"),
        ("fish", "complete -c sdsem"),
    ] {
        let out = run(sdsem().args(["completions", shell]));
        assert!(out.status.success(), "{shell}: {}", text(&out.stderr));
        let script = text(&out.stdout);
        assert!(script.contains(marker), "{shell}:\n{script}");
        assert!(script.contains("reconstruct") && script.contains("tilt-axis"));
    }
    // The bash script is valid bash.
    let script = run(sdsem().args(["completions", "bash"])).stdout;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sdsem.bash");
    std::fs::write(&path, script).unwrap();
    let check = run(Command::new("bash").arg("-n").arg(&path));
    assert!(check.status.success(), "{}", text(&check.stderr));
}

#[test]
fn man_pages_come_from_the_command_definition() {
    let out = run(sdsem().arg("man"));
    assert!(out.status.success(), "{}", text(&out.stderr));
    let page = text(&out.stdout);
    assert!(page.contains(".TH sdsem 1"), "{page}");
    for command in ["acquire", "reconstruct", "replay", "completions", "man"] {
        assert!(
            page.contains(&format!("sdsem\\-{command}(1)")),
            "{command} missing:\n{page}"
        );
    }
    let out = run(sdsem().args(["man", "flow"]));
    let page = text(&out.stdout);
    assert!(page.contains(".TH sdsem-flow 1"), "{page}");
    assert!(page.contains("\\-\\-out"), "{page}");
    assert!(page.contains("Examples:"), "{page}");
    // The evaluations live in sdsem-eval, not in the shipped binary.
    let out = run(sdsem().args(["man", "eval"]));
    assert!(!out.status.success(), "{}", text(&out.stdout));

    let out = run(sdsem().args(["man", "reconstrut"]));
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(
        err.contains("no command \"reconstrut\"") && err.contains("reconstruct"),
        "{err}"
    );
}

/// The reader of stdout is gone before the first line is written: the command ends quietly
/// (no panic, nothing on stderr), as a Unix filter does.
#[test]
fn a_closed_pipe_ends_the_command_quietly() {
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    let out = sdsem()
        .args(["check-config", "config/sim.toml"])
        .stdin(Stdio::null())
        .stdout(writer)
        .output()
        .unwrap();
    let err = text(&out.stderr);
    assert!(err.is_empty(), "stderr: {err}");
    assert!(
        out.status.success()
            || std::os::unix::process::ExitStatusExt::signal(&out.status) == Some(13),
        "{:?}",
        out.status
    );

    // The same through a shell pipeline.
    let out = run(Command::new("sh")
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .arg("-c")
        .arg(format!(
            "{} check-config config/sim.toml | head -1",
            env!("CARGO_BIN_EXE_sdsem")
        )));
    assert!(out.status.success());
    assert_eq!(
        text(&out.stdout),
        "# config/sim.toml: valid. Effective configuration:\n"
    );
    assert!(text(&out.stderr).is_empty(), "{}", text(&out.stderr));
}

#[test]
fn rectify_says_what_it_wrote() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right) = dome_pair(dir.path());
    let out_dir = dir.path().join("rect");
    let out = run(sdsem()
        .arg("rectify")
        .args([&left, &right])
        .arg("--out")
        .arg(&out_dir)
        .args(["--tilt-axis", "-90"]));
    let err = text(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("inlier matches, rectification error"), "{err}");
    let wrote = format!(
        "wrote {}/{{rectified_left.png, rectified_right.png, matches.png, rectification.json}}",
        out_dir.display()
    );
    assert!(err.contains(&wrote), "{err}");
    assert_eq!(text(&out.stdout), format!("{}\n", out_dir.display()));
    for name in ["rectified_left.png", "matches.png", "rectification.json"] {
        assert!(out_dir.join(name).is_file(), "{name}");
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out_dir.join("rectification.json")).unwrap())
            .unwrap();
    assert_eq!(json["schema_version"], 1);
}

/// A wrong tilt axis (the parallax is horizontal: φ = −90°, not 0°) is refused with the
/// hint to check it, by `rectify` and by `reconstruct`. `reconstruct` may first tell the
/// sparse stage done: the instrument's geometry replaces a refused sparse one, and the dense
/// stage's vertical flow then refuses it.
#[test]
fn a_wrong_tilt_axis_is_named_as_the_likely_cause() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right) = dome_pair(dir.path());
    for command in ["rectify", "reconstruct"] {
        let out = run(sdsem()
            .arg(command)
            .args([&left, &right])
            .arg("--out")
            .arg(dir.path().join(command))
            .args(
                ["--tilt-axis", "0", "--tilt", "6", "--pixel-size", "0.05"]
                    [..if command == "rectify" { 2 } else { 6 }]
                    .iter(),
            ));
        assert!(!out.status.success(), "{command} accepted φ = 0°");
        let err = text(&out.stderr);
        let lines: Vec<&str> = err.lines().collect();
        let (last, before) = lines.split_last().expect("an error line");
        assert!(last.starts_with("error: "), "{command}: {err}");
        assert!(
            before.iter().all(|l| l.contains(r#""stage":"sparse""#)),
            "{command}: only the sparse stage's time line may come before the error: {err}"
        );
        assert!(
            last.contains("check the tilt axis (--tilt-axis DEG, or reconstruction.tilt_axis_deg)"),
            "{command}: {err}"
        );
    }
}

#[test]
fn a_missing_file_is_named_once() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.tif");
    let cases: [Vec<std::ffi::OsString>; 3] = [
        vec![
            "reconstruct".into(),
            missing.clone().into(),
            missing.clone().into(),
            "--out".into(),
            dir.path().join("out").into(),
        ],
        vec!["inspect".into(), dir.path().join("nope.mcap").into()],
        vec![
            "replay".into(),
            dir.path().join("nope.mcap").into(),
            "--out".into(),
            dir.path().join("again").into(),
        ],
    ];
    for args in cases {
        let out = run(sdsem().args(&args));
        assert!(!out.status.success());
        let err = text(&out.stderr);
        assert_eq!(err.lines().count(), 1, "{err}");
        assert_eq!(err.matches("No such file or directory").count(), 1, "{err}");
        assert!(err.contains("nope."), "{err}");
    }
}

#[test]
fn a_truncated_tiff_is_called_incomplete() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right) = dome_pair(dir.path());
    let tags = sdsem::imaging::file::MicrographTags {
        pixel_size_um: Some(0.05),
        tilt_deg: Some(0.0),
        ..Default::default()
    };
    let tiff = dir.path().join("left.tif");
    let image = sdsem::imaging::file::load_image(&left).unwrap();
    sdsem::imaging::file::write_micrograph_tiff(
        &tiff,
        &image,
        &tags,
        sdsem::imaging::file::SampleDepth::Bits16,
    )
    .unwrap();
    let bytes = std::fs::read(&tiff).unwrap();
    let cut = dir.path().join("cut.tif");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let out = run(sdsem()
        .arg("reconstruct")
        .args([&cut, &right])
        .arg("--out")
        .arg(dir.path().join("out"))
        .args(["--tilt", "6"]));
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(
        err.contains(&format!("{} is incomplete", cut.display())) && err.contains("copy it again"),
        "{err}"
    );
    assert!(!err.contains("malformed"), "{err}");
}

#[test]
fn inverted_stage_limits_are_called_inverted() {
    let out = run(sdsem().args([
        "check-config",
        "config/sim.toml",
        "--set",
        "stage.tilt_min_deg=60",
        "--set",
        "stage.tilt_max_deg=-5",
    ]));
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(err.contains("the stage tilt limits are inverted"), "{err}");
    assert!(!err.contains("outside"), "{err}");
}

/// `reconstruct` on a pipe (not a terminal): one log line per stage with its time, in order.
/// The outputs are then never overwritten without `--force`: a second run into the same
/// directory is refused before any work, naming the files; `--force` replaces them without
/// following a link planted among them; an `--out` under a file is refused at once.
#[test]
fn reconstruct_tells_its_stages_and_never_overwrites_without_force() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right) = dome_pair(dir.path());
    let out_dir = dir.path().join("out");
    let reconstruct = |out: &Path, force: bool| {
        let mut cmd = sdsem();
        cmd.args(["--log-format", "text", "reconstruct"])
            .args([&left, &right])
            .arg("--out")
            .arg(out)
            .args(["--tilt", "6", "--pixel-size", "0.05", "--tilt-axis", "-90"]);
        if force {
            cmd.arg("--force");
        }
        run(&mut cmd)
    };
    let first = reconstruct(&out_dir, false);
    let log = text(&first.stderr);
    assert!(first.status.success(), "{log}");
    let mut at = 0;
    for stage in [
        "sparse stage (SIFT, matching, ORSA, rectification): ",
        "dense stage (SIFT flow, left–right check, bilateral grid): ",
        "heights on the left micrograph's grid: ",
        "writing the outputs: ",
    ] {
        let found = log[at..]
            .find(stage)
            .unwrap_or_else(|| panic!("no line for {stage:?} after byte {at} in\n{log}"));
        at += found + stage.len();
        let seconds = log[at..].split(" s").next().unwrap();
        assert!(seconds.parse::<f64>().is_ok(), "{stage}{seconds}");
    }
    let report = std::fs::read(out_dir.join("report.json")).unwrap();

    let again = reconstruct(&out_dir, false);
    assert!(!again.status.success());
    let err = text(&again.stderr);
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(
        err.contains("already holds height.tif, height.gsf, pointcloud.ply")
            && err.contains("report.json")
            && err.contains("give --force to replace them"),
        "{err}"
    );
    assert!(!err.contains("sparse stage"), "work began: {err}");
    assert_eq!(std::fs::read(out_dir.join("report.json")).unwrap(), report);

    // --force replaces the outputs; a link among them is replaced, its target left alone.
    let victim = dir.path().join("victim");
    std::fs::write(&victim, b"precious").unwrap();
    std::fs::remove_file(out_dir.join("mesh.ply")).unwrap();
    std::os::unix::fs::symlink(&victim, out_dir.join("mesh.ply")).unwrap();
    let forced = reconstruct(&out_dir, true);
    assert!(forced.status.success(), "{}", text(&forced.stderr));
    assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
    assert!(
        std::fs::symlink_metadata(out_dir.join("mesh.ply"))
            .unwrap()
            .is_file()
    );
    assert_ne!(std::fs::read(out_dir.join("report.json")).unwrap(), report);

    let notes = dir.path().join("notes.txt");
    std::fs::write(&notes, "x").unwrap();
    let under = reconstruct(&notes.join("out"), false);
    assert!(!under.status.success());
    let err = text(&under.stderr);
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(
        err.contains(&format!("{} is a file, not a directory", notes.display())),
        "{err}"
    );
    assert!(!err.contains("sparse stage"), "work began: {err}");
}

/// `flow --out` onto an existing file: refused before any work, the file kept; `--force`
/// replaces it.
#[test]
fn flow_refuses_an_existing_file_without_force() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = dome_pair(dir.path());
    let flo = dir.path().join("a.flo");
    std::fs::write(&flo, b"precious").unwrap();
    let flow = |force: bool| {
        let mut cmd = sdsem();
        cmd.arg("flow").args([&a, &b]).arg("--out").arg(&flo);
        if force {
            cmd.arg("--force");
        }
        run(&mut cmd)
    };
    let refused = flow(false);
    assert!(!refused.status.success());
    let err = text(&refused.stderr);
    assert!(
        err.contains("already holds a.flo") && err.contains("--force"),
        "{err}"
    );
    assert_eq!(std::fs::read(&flo).unwrap(), b"precious");
    let forced = flow(true);
    assert!(forced.status.success(), "{}", text(&forced.stderr));
    assert_eq!(&std::fs::read(&flo).unwrap()[..4], b"PIEH");
}

/// A configuration error names the layer that gave the value (the file, an `SDSEM_`
/// variable, a `--set`), the key, and the key or value meant when it is a near miss.
#[test]
fn configuration_errors_name_their_layer_and_the_key_meant() {
    let dir = tempfile::tempdir().unwrap();
    let check = |file: &Path, set: &[&str], env: &[(&str, &str)]| {
        let mut cmd = sdsem();
        cmd.arg("check-config").arg(file);
        for s in set {
            cmd.args(["--set", s]);
        }
        for (k, v) in env {
            cmd.env(k, v);
        }
        let out = run(&mut cmd);
        assert!(!out.status.success());
        let err = text(&out.stderr);
        assert_eq!(err.lines().count(), 1, "{err}");
        err
    };
    let sim = Path::new("config/sim.toml");
    let err = check(sim, &["reconstruction.dense.alfa=1"], &[]);
    assert!(
        err.contains("in --set reconstruction.dense.alfa=1: ")
            && err.contains("did you mean reconstruction.dense.alpha?"),
        "{err}"
    );
    assert!(!err.contains("sim.toml"), "blamed on the file: {err}");
    let err = check(sim, &[], &[("SDSEM_RECONSTRUCTION__MODE", "papr")]);
    assert!(
        err.contains("in environment variable SDSEM_RECONSTRUCTION__MODE=\"papr\": ")
            && err.contains(
                "reconstruction.mode = \"papr\" is not a known value: did you mean \"paper\"?"
            ),
        "{err}"
    );
    let file = dir.path().join("bad.toml");
    std::fs::write(&file, "[reconstruction]\nmdoe = \"paper\"\n").unwrap();
    let err = check(&file, &[], &[]);
    assert!(
        err.contains(&format!("in {}: ", file.display()))
            && err.contains("unknown key reconstruction.mdoe: did you mean reconstruction.mode?"),
        "{err}"
    );
}

/// A job's `[reconstruction]` table takes the configuration's own keys (`mode = "paper"`),
/// and a near miss there is answered with the key meant.
#[test]
fn a_job_takes_reconstruction_keys_in_their_natural_form() {
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join("spool");
    let submit = |body: &str| {
        let job = dir.path().join("job.toml");
        std::fs::write(
            &job,
            format!("name = \"j\"\nstart_tilt = 0\nend_tilt = 5\n{body}"),
        )
        .unwrap();
        run(sdsem().arg("submit").arg(&job).arg("--spool").arg(&spool))
    };
    let out = submit("[reconstruction]\nmode = \"paper\"\n[reconstruction.dense]\nlevels = 3\n");
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        text(&out.stdout).starts_with("queued job 1 (j)"),
        "{}",
        text(&out.stdout)
    );
    let out = submit("[reconstruction]\ndense.alfa = 2.0\n");
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(
        err.contains(
            "[reconstruction] reconstruction.dense.alfa = 2.0: unknown field `alfa`: \
             did you mean reconstruction.dense.alpha?"
        ),
        "{err}"
    );
}
