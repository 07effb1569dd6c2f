"""`cadsplat rig list` with OAK devices (the depthai fake), one in use, and with none."""

from __future__ import annotations

import rig.oak
from deploy.cli import main
from tests.rig.fake_depthai import FakeDai, Hardware, Sensor


def test_rig_list_shows_devices_sockets_sensors_and_sync_modes(monkeypatch, capsys):
    ffc = Hardware("18443010D1C2A41200", "RVC2", [Sensor("CAM_A", "OV9282", 1280, 800), Sensor("CAM_B", "IMX378", 4056, 3040)])
    oak4 = Hardware("OAK4-0001", "RVC4", [Sensor("CAM_A", "IMX586", 4000, 3000)], product="OAK4-D")
    busy = Hardware("14442C10D13EABCE00", "RVC2", [Sensor("CAM_A", "AR0234", 1920, 1200)])
    dai = FakeDai(ffc, oak4, busy)
    running_rig = dai.Device(dai.DeviceInfo(busy.device_id))
    monkeypatch.setattr(rig.oak, "import_depthai", lambda: dai)
    assert main(["rig", "list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[:2] == ["OAK devices below come from a depthai fake, not from hardware.", "OAK devices: 3 found"]
    assert "  18443010D1C2A41200  OAK-FFC-4P  RVC2  2 sockets" in out
    assert "    CAM_A  OV9282   1280x800  sync: software, fsin (snapshot on FSIN edge)" in out
    assert "    CAM_B  IMX378   4056x3040  sync: software" in out
    assert "    CAM_A  IMX586   4000x3000  sync: software, fsin (continuous FSYNC, device slave)" in out
    assert any(
        line.startswith("  14442C10D13EABCE00  RVC2  X_LINK_BOOTED: OAK 14442C10D13EABCE00 cannot be opened to list its cameras")
        for line in out
    )
    running_rig.close()


def test_rig_list_without_any_device_says_so(monkeypatch, capsys):
    monkeypatch.setattr(rig.oak, "import_depthai", lambda: FakeDai())
    assert main(["rig", "list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1] == "OAK devices: none found (depthai sees no OAK on USB or the network)."


def test_rig_list_checks_the_configured_oak_cameras(monkeypatch, capsys, tmp_path):
    dai = FakeDai(Hardware("18443010D1C2A41200", "RVC2", [Sensor("CAM_A", "OV9282", 1280, 800)]))
    monkeypatch.setattr(rig.oak, "import_depthai", lambda: dai)
    toml = tmp_path / "rig.toml"
    toml.write_text(
        "\n".join(
            f'[[cameras]]\nid = "{i}"\ndevice = "{d}"\nsocket = "{s}"'
            for i, d, s in [("cam0", "18443010D1C2A41200", "CAM_A"), ("cam1", "18443010D1C2A41200", "CAM_B"), ("cam2", "NOPE", "CAM_A")]
        )
    )
    assert main(["rig", "list", "--config", str(toml)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-3:-1] == ["camera cam1: OAK 18443010D1C2A41200 has no camera on CAM_B.", "camera cam2: OAK NOPE is not connected."]
