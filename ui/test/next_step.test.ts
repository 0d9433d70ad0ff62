import { describe, expect, it } from "vitest";
import { renderFailureNextStep, volumeRefusalNextStep } from "../src/next_step";

describe("next step after a refusal (7.44)", () => {
  it("a volume that is not readable: which files are taken, and add it again", () => {
    const t = volumeRefusalNextStep("volume t1.nii.gz: not a readable volume: t1.nii.gz: not a readable NIfTI file");
    expect(t).toBe("volume t1.nii.gz: not a readable volume: t1.nii.gz: not a readable NIfTI file. " +
      "Check that it is a NIfTI (.nii, .nii.gz), NRRD (.nrrd) or MetaImage (.mha) file or a DICOM folder, then add it again.");
  });
  it("other refusals pass unchanged (no wrong advice)", () => {
    expect(volumeRefusalNextStep("case 7: not found")).toBe("case 7: not found");
  });
  it("the daemon's own MRI unreadable: names the file and data.t1, no promise that waiting helps", () => {
    const t = renderFailureNextStep("render: the volume could not be loaded: /tmp/x/not-an-mri.nii.gz: not a readable NIfTI file", false);
    expect(t).toContain("its own MRI file /tmp/x/not-an-mri.nii.gz");
    expect(t).toContain("`data.t1`");
    expect(t).toContain("restart cortexfused");
    expect(t).not.toContain("when the daemon is ready");
  });
  it("the case's own MRI unreadable: add it again", () => {
    const t = renderFailureNextStep("render: the volume could not be loaded: case 3 volume 2: not a readable NIfTI file", true);
    expect(t).toContain("add it again on Contents");
    expect(t).not.toContain("data.t1");
  });
  it("a passing failure keeps the try-again advice", () => {
    expect(renderFailureNextStep("render: busy", false)).toBe("render: busy. The view's settings are kept; try again when the daemon is ready.");
  });
});
