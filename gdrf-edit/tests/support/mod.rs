//! What the server tests share: a `gdrf-edit serve` process on a free loopback port, and
//! the binary's own HTTP client (the server's protocol, and WebDriver's).
#![allow(dead_code)]
#[path = "../../src/serve/client.rs"]
mod client;

pub use client::Answer;

/// One request; a connection that fails fails the test, naming the request.
pub fn request(port: u16, method: &str, path: &str, host: &str, body: &[u8]) -> Answer {
    client::request(port, method, path, host, body).unwrap_or_else(|e| panic!("{method} {path} on port {port}: {e}"))
}

/// A `gdrf-edit serve` process on a free loopback port, killed when dropped.
pub struct Served(pub client::Served);

impl Served {
    /// Starts `gdrf-edit serve --port 0 --device cpu ARGS` and waits for its address.
    pub fn start(args: &[&str]) -> Self {
        let exe = std::path::Path::new(env!("CARGO_BIN_EXE_gdrf-edit"));
        Self(client::Served::start(exe, args).unwrap_or_else(|e| panic!("gdrf-edit serve {args:?}: {e}")))
    }

    pub fn port(&self) -> u16 {
        self.0.port
    }

    pub fn host(&self) -> String {
        self.0.host()
    }

    pub fn get(&self, path: &str) -> Answer {
        request(self.port(), "GET", path, &self.host(), &[])
    }

    pub fn post(&self, path: &str, body: &[u8]) -> Answer {
        request(self.port(), "POST", path, &self.host(), body)
    }
}

impl std::ops::DerefMut for Served {
    fn deref_mut(&mut self) -> &mut client::Served {
        &mut self.0
    }
}

impl std::ops::Deref for Served {
    type Target = client::Served;
    fn deref(&self) -> &client::Served {
        &self.0
    }
}
