//! The discovery settings a ROS 2 user sets in the environment, applied to the node's DDS
//! participant (`rustdds`):
//!
//! * `ROS_AUTOMATIC_DISCOVERY_RANGE` (ROS 2 Jazzy): `SUBNET` (default) and `SYSTEM_DEFAULT`
//!   discover on every interface; `LOCALHOST` uses the loopback interface only (multicast
//!   joined and sent on it, only `127.0.0.1` advertised), so that peers on other hosts neither
//!   find the node nor are found; `OFF` is refused (the node will not start), because rustdds
//!   has no setting to turn automatic discovery off, and a node that ignored it would be found
//!   by others;
//! * `ROS_LOCALHOST_ONLY=1` (before Jazzy): as `LOCALHOST`; it wins over
//!   `ROS_AUTOMATIC_DISCOVERY_RANGE`, as in ROS 2's middlewares;
//! * `ROS_STATIC_PEERS` (Jazzy): refused with a warning and otherwise ignored (rustdds has no
//!   unicast initial peers): the node is found only by automatic discovery.
//!
//! [`Discovery::from_env`] reads them, with the lines the node logs about them;
//! [`Discovery::participant`] builds the participant.

use ros2_client::dds::rustdds::{DomainParticipant, DomainParticipantBuilder};
use std::net::{IpAddr, Ipv4Addr};

/// The range of automatic discovery.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Range {
    /// Every interface (`SUBNET`, `SYSTEM_DEFAULT` or unset).
    Subnet,
    /// The loopback interface only (`LOCALHOST`, or `ROS_LOCALHOST_ONLY=1`).
    Localhost,
}

/// Discovery settings read from the environment.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Discovery {
    /// The range honoured.
    pub range: Range,
    /// What is honoured, to log at start-up (info).
    pub honoured: Vec<String>,
    /// What is ignored and why, to log at start-up (warnings).
    pub ignored: Vec<String>,
}

impl Discovery {
    /// Reads `ROS_AUTOMATIC_DISCOVERY_RANGE`, `ROS_LOCALHOST_ONLY` and `ROS_STATIC_PEERS`
    /// through `var` (the process environment: `|name| std::env::var(name).ok()`).
    ///
    /// Errors, with the reason, on `OFF` and on a range ROS 2 does not define.
    pub fn from_env(var: impl Fn(&str) -> Option<String>) -> Result<Self, String> {
        let mut honoured = Vec::new();
        let mut ignored = Vec::new();
        let localhost_only = match var("ROS_LOCALHOST_ONLY").as_deref().map(str::trim) {
            None | Some("") | Some("0") => false,
            Some("1") => true,
            Some(other) => {
                ignored.push(format!(
                    "ROS_LOCALHOST_ONLY `{other}` ignored (only 1 turns it on)"
                ));
                false
            }
        };
        let requested = var("ROS_AUTOMATIC_DISCOVERY_RANGE")
            .map(|text| text.trim().to_ascii_uppercase())
            .filter(|text| !text.is_empty());
        let range = if localhost_only {
            if let Some(other) = requested.as_deref().filter(|r| *r != "LOCALHOST") {
                ignored.push(format!(
                    "ROS_AUTOMATIC_DISCOVERY_RANGE={other} overridden by ROS_LOCALHOST_ONLY=1"
                ));
            }
            honoured
                .push("ROS_LOCALHOST_ONLY=1: discovery on the loopback interface only".to_string());
            Range::Localhost
        } else {
            match requested.as_deref() {
                None | Some("SUBNET") | Some("SYSTEM_DEFAULT") => Range::Subnet,
                Some("LOCALHOST") => {
                    honoured.push(
                        "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST: discovery on the loopback \
                         interface only"
                            .to_string(),
                    );
                    Range::Localhost
                }
                Some("OFF") => {
                    return Err("ROS_AUTOMATIC_DISCOVERY_RANGE=OFF is not supported: this \
                                node's DDS (rustdds) has no setting to turn automatic \
                                discovery off; use LOCALHOST, or unset it"
                        .to_string())
                }
                Some(other) => {
                    return Err(format!(
                        "ROS_AUTOMATIC_DISCOVERY_RANGE `{other}` is not one of SUBNET, \
                         LOCALHOST, OFF, SYSTEM_DEFAULT"
                    ))
                }
            }
        };
        if let Some(peers) = var("ROS_STATIC_PEERS").filter(|p| !p.trim().is_empty()) {
            ignored.push(format!(
                "ROS_STATIC_PEERS `{peers}` ignored: this node's DDS (rustdds) has no static \
                 peers; it is found by automatic discovery only"
            ));
        }
        Ok(Discovery {
            range,
            honoured,
            ignored,
        })
    }

    /// Logs what is honoured (info) and what is ignored (warnings).
    pub fn log(&self) {
        for line in &self.honoured {
            log::info!("{line}");
        }
        for line in &self.ignored {
            log::warn!("{line}");
        }
    }

    /// The DDS participant on `domain_id` with these settings.
    pub fn participant(&self, domain_id: u16) -> Result<DomainParticipant, String> {
        let builder = DomainParticipantBuilder::new(domain_id);
        let builder = match self.range {
            Range::Subnet => builder,
            Range::Localhost => builder.with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)]),
        };
        builder
            .build()
            .map_err(|e| format!("cannot start DDS: {e:?}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(vars: &[(&str, &str)]) -> Result<Discovery, String> {
        Discovery::from_env(|name| {
            vars.iter()
                .find(|(n, _)| *n == name)
                .map(|(_, v)| v.to_string())
        })
    }

    #[test]
    fn default_and_subnet_discover_everywhere_silently() {
        for vars in [
            &[][..],
            &[("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")],
            &[("ROS_AUTOMATIC_DISCOVERY_RANGE", "system_default")],
            &[("ROS_LOCALHOST_ONLY", "0"), ("ROS_STATIC_PEERS", "")],
        ] {
            let d = read(vars).expect("accepted");
            assert_eq!(d.range, Range::Subnet, "{vars:?}");
            assert!(
                d.honoured.is_empty() && d.ignored.is_empty(),
                "{vars:?}: {d:?}"
            );
        }
    }

    #[test]
    fn localhost_from_either_variable() {
        let d = read(&[("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")]).expect("accepted");
        assert_eq!(d.range, Range::Localhost);
        assert!(d.honoured[0].contains("loopback interface only"), "{d:?}");
        let d = read(&[
            ("ROS_LOCALHOST_ONLY", "1"),
            ("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET"),
        ])
        .expect("accepted");
        assert_eq!(d.range, Range::Localhost);
        assert!(
            d.ignored[0].contains("overridden by ROS_LOCALHOST_ONLY=1"),
            "{d:?}"
        );
    }

    #[test]
    fn off_and_unknown_ranges_are_refused() {
        let e = read(&[("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")]).expect_err("refused");
        assert!(e.contains("OFF is not supported"), "{e}");
        let e = read(&[("ROS_AUTOMATIC_DISCOVERY_RANGE", "LAN")]).expect_err("refused");
        assert!(e.contains("`LAN` is not one of"), "{e}");
    }

    #[test]
    fn static_peers_and_odd_localhost_only_are_noted() {
        let d = read(&[
            ("ROS_STATIC_PEERS", "10.0.0.2;robot"),
            ("ROS_LOCALHOST_ONLY", "yes"),
        ])
        .expect("accepted");
        assert_eq!(d.range, Range::Subnet);
        assert!(d
            .ignored
            .iter()
            .any(|n| n.contains("ROS_STATIC_PEERS `10.0.0.2;robot` ignored")));
        assert!(d
            .ignored
            .iter()
            .any(|n| n.contains("ROS_LOCALHOST_ONLY `yes` ignored")));
    }
}
