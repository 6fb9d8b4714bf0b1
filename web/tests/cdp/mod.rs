//! A Chrome DevTools-protocol client over a pipe, std only (issue 47): Chromium started with
//! `--remote-debugging-pipe` reads NUL-terminated JSON commands on its fd 3 and writes
//! NUL-terminated replies and events on its fd 4. The browser tests use it to read the page's
//! state (`evaluate`) and to send it real input: mouse presses, moves and releases and key
//! presses, as a user's would arrive (Input.dispatch*), which the capture hook cannot.

use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::os::fd::{FromRawFd, OwnedFd, RawFd};
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

/// How long one protocol command may take to be answered (a frame on SwiftShader included):
/// it bounds a hang, it times nothing.
const REPLY_DEADLINE: Duration = Duration::from_secs(120);

pub struct Cdp {
    child: Child,
    commands: File,
    messages: mpsc::Receiver<Value>,
    next_id: u64,
    session: String,
    log: std::path::PathBuf,
    _profile: tempfile::TempDir,
    // Dropped after the child is killed (fields drop after `Drop::drop`).
    _turn: std::sync::MutexGuard<'static, ()>,
}

impl Drop for Cdp {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A pipe whose two ends close on exec (the child gets copies at fds 3 and 4 instead).
fn pipe() -> (OwnedFd, OwnedFd) {
    let mut fds: [RawFd; 2] = [-1, -1];
    // SAFETY: pipe2 writes two new descriptors into the array it is given.
    let rc = unsafe { libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC) };
    assert_eq!(rc, 0, "pipe2: {}", std::io::Error::last_os_error());
    // SAFETY: both descriptors are new and owned by nothing else.
    unsafe { (OwnedFd::from_raw_fd(fds[0]), OwnedFd::from_raw_fd(fds[1])) }
}

impl Cdp {
    /// Headless Chromium on `url` in a window of `window` CSS pixels (the flags of
    /// browser.rs's `Browser`: WebGPU on SwiftShader), driven over the pipe, attached to its
    /// page.
    pub fn open(url: &str, scratch: &Path, window: [u32; 2]) -> Cdp {
        use std::os::fd::AsRawFd;
        let turn = crate::ONE_BROWSER_AT_A_TIME
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        let profile = tempfile::tempdir().expect("browser profile folder");
        let log = scratch.join("chromium.log");
        let log_file = File::create(&log).expect("browser log file");
        let (browser_reads, we_write) = pipe();
        let (we_read, browser_writes) = pipe();
        let (child_in, child_out) = (browser_reads.as_raw_fd(), browser_writes.as_raw_fd());
        let mut command = Command::new(crate::chromium());
        command
            .args([
                "--headless=new",
                "--no-sandbox",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-quic",
                "--enable-unsafe-webgpu",
                "--enable-unsafe-swiftshader",
                "--use-webgpu-adapter=swiftshader",
                "--enable-gpu",
                "--enable-features=Vulkan",
                "--use-vulkan=swiftshader",
                "--use-angle=swiftshader",
                "--enable-logging=stderr",
                "--force-device-scale-factor=1",
                "--remote-debugging-pipe",
            ])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg(format!("--window-size={},{}", window[0], window[1]))
            .arg(url)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log_file);
        // SAFETY: only async-signal-safe calls (fcntl, dup2) between fork and exec.
        unsafe {
            command.pre_exec(move || {
                // Moved above 4 first, so that neither end is overwritten by the other's dup2
                // when the pipe itself got fd 3 or 4.
                let high_in = libc::fcntl(child_in, libc::F_DUPFD_CLOEXEC, 10);
                let high_out = libc::fcntl(child_out, libc::F_DUPFD_CLOEXEC, 10);
                if high_in < 0
                    || high_out < 0
                    || libc::dup2(high_in, 3) < 0
                    || libc::dup2(high_out, 4) < 0
                {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = command
            .spawn()
            .unwrap_or_else(|e| panic!("starting Chromium: {e}"));
        // The browser's ends now live in the child only: its exit then ends our reads.
        drop((browser_reads, browser_writes));
        let (sender, messages) = mpsc::channel();
        let reader = BufReader::new(File::from(we_read));
        std::thread::Builder::new()
            .name("cdp-pipe-reader".into())
            .spawn(move || {
                for message in reader.split(0) {
                    let Ok(bytes) = message else { break };
                    let Ok(value) = serde_json::from_slice::<Value>(&bytes) else {
                        continue;
                    };
                    if sender.send(value).is_err() {
                        break;
                    }
                }
            })
            .expect("starting the DevTools pipe's reader");
        let mut cdp = Cdp {
            child,
            commands: File::from(we_write),
            messages,
            next_id: 0,
            session: String::new(),
            log,
            _profile: profile,
            _turn: turn,
        };
        let target = cdp.wait_for("the page's DevTools target", REPLY_DEADLINE, |cdp| {
            let targets = cdp.browser_command("Target.getTargets", json!({}));
            targets["targetInfos"]
                .as_array()?
                .iter()
                .find(|t| t["type"] == "page")
                .and_then(|t| t["targetId"].as_str())
                .map(str::to_owned)
        });
        let attached = cdp.browser_command(
            "Target.attachToTarget",
            json!({ "targetId": target, "flatten": true }),
        );
        cdp.session = attached["sessionId"]
            .as_str()
            .unwrap_or_else(|| panic!("Target.attachToTarget gave no sessionId: {attached}"))
            .to_owned();
        // Headless windows are never the focused one: without this the canvas's focus (and
        // so its key events) would depend on the window manager there is none of.
        cdp.command(
            "Emulation.setFocusEmulationEnabled",
            json!({ "enabled": true }),
        );
        cdp
    }

    /// The console lines the page wrote (for failure messages).
    pub fn console(&self) -> String {
        std::fs::read_to_string(&self.log)
            .unwrap_or_default()
            .lines()
            .filter(|l| l.contains("CONSOLE") || l.contains("strata") || l.contains("WebGPU"))
            .collect::<Vec<_>>()
            .join("\n")
    }

    /// A command to the browser itself (not the page: `Browser.setDownloadBehavior`).
    pub fn browser_command(&mut self, method: &str, params: Value) -> Value {
        self.send(method, params, None)
    }

    /// A command to the attached page; its result.
    pub fn command(&mut self, method: &str, params: Value) -> Value {
        let session = self.session.clone();
        self.send(method, params, Some(&session))
    }

    fn send(&mut self, method: &str, params: Value, session: Option<&str>) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let mut message = json!({ "id": id, "method": method, "params": params });
        if let Some(session) = session {
            message["sessionId"] = json!(session);
        }
        let mut bytes = serde_json::to_vec(&message).expect("a command serialises");
        bytes.push(0);
        self.commands
            .write_all(&bytes)
            .unwrap_or_else(|e| panic!("sending {method} to Chromium: {e}; {}", self.console()));
        let deadline = Instant::now() + REPLY_DEADLINE;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            // Events (no id) and other replies are not waited for: dropped.
            match self.messages.recv_timeout(left) {
                Ok(reply) if reply["id"] == id => {
                    if let Some(error) = reply.get("error") {
                        panic!("Chromium refused {method}: {error}");
                    }
                    return reply["result"].clone();
                }
                Ok(_) => {}
                Err(_) => panic!(
                    "Chromium did not answer {method} within {REPLY_DEADLINE:?}; its console:\n{}",
                    self.console()
                ),
            }
        }
    }

    /// The value of the JavaScript expression `js` in the page (a promise is awaited).
    pub fn evaluate(&mut self, js: &str) -> Value {
        let result = self.command(
            "Runtime.evaluate",
            json!({ "expression": js, "returnByValue": true, "awaitPromise": true }),
        );
        if let Some(exception) = result.get("exceptionDetails") {
            panic!("evaluating `{js}` threw: {exception}");
        }
        result["result"]["value"].clone()
    }

    /// Polls `probe` until it gives a value; panics naming `what` at the deadline.
    pub fn wait_for<T>(
        &mut self,
        what: &str,
        deadline: Duration,
        mut probe: impl FnMut(&mut Cdp) -> Option<T>,
    ) -> T {
        let until = Instant::now() + deadline;
        loop {
            if let Some(value) = probe(self) {
                return value;
            }
            if Instant::now() > until {
                let hash = self.evaluate("location.hash");
                panic!(
                    "waited {deadline:?} for {what}; the page's link: {hash}; its console:\n{}",
                    self.console()
                );
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Returns once the page has drawn two animation frames: input sent before has been
    /// through egui's update (eframe repaints on input in its own animation frame).
    pub fn next_frames(&mut self) {
        self.evaluate(
            "new Promise(done => requestAnimationFrame(() => requestAnimationFrame(() => done(true))))",
        );
    }

    fn mouse(&mut self, kind: &str, x: f64, y: f64, buttons: u32) {
        self.command(
            "Input.dispatchMouseEvent",
            json!({
                "type": kind, "x": x, "y": y, "button": if kind == "mouseMoved" && buttons == 0 { "none" } else { "left" },
                "buttons": buttons, "clickCount": 1,
            }),
        );
        self.next_frames();
    }

    /// Moves the pointer to (x, y) CSS pixels, with the left button held when `held`.
    pub fn mouse_move(&mut self, x: f64, y: f64, held: bool) {
        self.mouse("mouseMoved", x, y, u32::from(held));
    }

    pub fn mouse_press(&mut self, x: f64, y: f64) {
        self.mouse("mousePressed", x, y, 1);
    }

    pub fn mouse_release(&mut self, x: f64, y: f64) {
        self.mouse("mouseReleased", x, y, 0);
    }

    /// A left-button drag from `from` to `to` in `steps` moves (each its own frame).
    pub fn drag(&mut self, from: [f64; 2], to: [f64; 2], steps: u32) {
        self.mouse_move(from[0], from[1], false);
        self.mouse_press(from[0], from[1]);
        for step in 1..=steps {
            let t = f64::from(step) / f64::from(steps);
            self.mouse_move(
                from[0] + (to[0] - from[0]) * t,
                from[1] + (to[1] - from[1]) * t,
                true,
            );
        }
        self.mouse_release(to[0], to[1]);
    }

    /// A left click at (x, y).
    pub fn click(&mut self, x: f64, y: f64) {
        self.mouse_move(x, y, false);
        self.mouse_press(x, y);
        self.mouse_release(x, y);
    }

    /// A left click at (x, y) whose press and release go out back to back, after a move
    /// there: egui takes a press held longer than its click time (0.8 s) as a drag's start,
    /// and on SwiftShader the frames [`Cdp::click`] waits between them can exceed it (a large
    /// window's frames on two busy cores do).
    pub fn quick_click(&mut self, x: f64, y: f64) {
        self.mouse_move(x, y, false);
        for (kind, buttons) in [("mousePressed", 1), ("mouseReleased", 0)] {
            self.command(
                "Input.dispatchMouseEvent",
                json!({ "type": kind, "x": x, "y": y, "button": "left", "buttons": buttons, "clickCount": 1 }),
            );
        }
        self.next_frames();
    }

    /// Presses and releases one key: `key` as KeyboardEvent.key ("a"), `code` as
    /// KeyboardEvent.code ("KeyA"); the virtual key code is a letter's or digit's.
    pub fn key(&mut self, key: &str, code: &str) {
        let virtual_code = key
            .chars()
            .next()
            .filter(|c| key.len() == 1 && c.is_ascii_alphanumeric())
            .map(|c| u32::from(c.to_ascii_uppercase()))
            .unwrap_or_else(|| panic!("key({key:?}): only letters and digits have codes here"));
        for kind in ["keyDown", "keyUp"] {
            let mut event = json!({
                "type": kind, "key": key, "code": code, "windowsVirtualKeyCode": virtual_code,
                "nativeVirtualKeyCode": virtual_code,
            });
            if kind == "keyDown" {
                event["text"] = json!(key);
            }
            self.command("Input.dispatchKeyEvent", event);
        }
        self.next_frames();
    }
}
