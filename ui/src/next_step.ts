// The next step after a refusal (issue 7, 7.44): the daemon's one-line error says what went
// wrong; these add what the person at the cart should do about it.

/** A volume upload or a USB stick import refused as "not a readable volume" (or any 400 about
 *  the file): say which files are taken and to add it again. Other errors pass unchanged. */
export function volumeRefusalNextStep(message: string): string {
  const m = message.trim();
  if (!/not a readable volume|not a readable (NIfTI|NRRD|MetaImage|DICOM)|unsupported volume|not a volume/i.test(m)) return m;
  const s = /[.!?)]$/.test(m) ? m : `${m}.`;
  return `${s} Check that it is a NIfTI (.nii, .nii.gz), NRRD (.nrrd) or MetaImage (.mha) file or a DICOM folder, then add it again.`;
}

/** A render that failed. `caseHasT1`: the case has an MRI of its own (else the daemon's
 *  configured MRI, `data.t1`, is rendered). A volume that cannot be loaded will not load by
 *  waiting: the daemon's own file needs its config fixed; the case's needs a new upload. */
export function renderFailureNextStep(message: string, caseHasT1: boolean): string {
  const m = message.trim();
  const s = /[.!?)]$/.test(m) ? m : `${m}.`;
  if (/could not be loaded|not a readable/i.test(m)) {
    if (!caseHasT1) {
      const file = /loaded: ([^:]+):/.exec(m)?.[1]?.trim();
      return `${s} The daemon cannot read its own MRI file${file ? ` ${file}` : ""}: trying again will not help. ` +
        "A technician must point `data.t1` in the daemon's config (/etc/cortexfuse/cortexfused.json) at a readable MRI and restart cortexfused.";
    }
    return `${s} The case's MRI cannot be read: add it again on Contents (a NIfTI, NRRD or MetaImage file or a DICOM folder).`;
  }
  return `${s} The view's settings are kept; try again when the daemon is ready.`;
}
